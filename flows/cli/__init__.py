"""The ``swathflow`` command line: the parser (:mod:`.main`) and the command handlers
(:mod:`.commands`)."""
from swathflow.flows.cli.main import build_parser, main

__all__ = ["build_parser", "main"]
