"""Rerun race recordings as files: the layout a recording opens with (``blueprint``) and whether a
file is whole (``integrity``). Writers and readers of the race data import these; this package
imports nothing else of the project."""
