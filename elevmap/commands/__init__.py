"""One module per ``elevmap`` subcommand; :mod:`elevmap.cli` parses the command line and calls them."""
