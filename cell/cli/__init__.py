"""The ``cell`` command line."""
