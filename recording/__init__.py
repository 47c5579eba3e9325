"""Rerun race recordings as files: the layout a recording opens with (``blueprint``), whether a file
is whole (``integrity``) and the live viewers a recording also streams to (``live``). Writers and
readers of the race data import these; this package imports nothing else of the project."""
