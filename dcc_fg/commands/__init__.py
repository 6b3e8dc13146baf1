"""The ``dcc-fg`` subcommands: each module turns command-line arguments into options dataclasses,
runs the library and writes the outputs. :mod:`dcc_fg.cli` only assembles them."""
