"""The ``parksim`` subcommands, one module each (``add_parser`` + ``run``), and their shared parsing helpers."""

__all__: list[str] = []
