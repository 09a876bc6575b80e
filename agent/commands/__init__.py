"""One module per ``vlp-agent`` subcommand; each has ``add_parser(subparsers)`` and ``run(args) -> int``."""
