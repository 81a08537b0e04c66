"""The symbolic layer: the only part of volcal that imports SymPy.

``dual`` holds first-order dual matrices (eps^2 = 0), ``transforms`` the elementary
homogeneous transforms, ``chain`` turns a :class:`~volcal.model.spec.MachineSpec` into the
first-order and the exact tool-point expressions.
"""

from volcal.model.symbolic.chain import ChainExpressions, build_chain

__all__ = ["ChainExpressions", "build_chain"]
