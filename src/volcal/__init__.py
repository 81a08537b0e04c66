"""volcal: identify the geometric errors of machine tools from multilateration lengths.

Units inside the code: lengths in mm, angles in rad. Files carry units in column names.
"""

__version__ = "0.1.0"
