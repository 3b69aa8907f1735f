"""One module per top-level command; cli.py loads them on demand."""
