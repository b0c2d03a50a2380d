"""Command-line interface: ``tissuecast SUBCOMMAND ...`` (see :func:`tissuecast.cli.main.main`)."""
