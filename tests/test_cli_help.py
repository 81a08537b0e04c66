"""Every command's --help renders as written."""


def test_help_texts_show_no_doubled_percent_signs():
    """argparse formats %-signs in help strings but not in descriptions: a description
    written with '%%' prints it doubled."""
    from volcal.cli.main import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    for name, p in sub.choices.items():
        assert "%%" not in p.format_help(), name
