"""Strict input files and safe output files, shared by every loader (docs/file-formats.md).

    from fileio import load_json, validate, atomic_write_text
"""
from .read import (InputFileError, MAX_BYTES, MAX_DEPTH, MAX_LINE, check_depth, check_line_length, decode_utf8,
                   load_json, load_toml, parse_json, parse_toml, read_bytes, read_text)
from .schema import (AnyOf, Array, Boolean, FieldSpec, Invalid, ListOf, Number, String, Table, Tagged,
                     table_from_dataclass, unknown_key_message, validate)
from .write import (OutputFileError, OutputTarget, atomic_path, atomic_write_bytes, atomic_write_text, atomic_write_with,
                    check_output_dir, check_output_path, output_target)

__all__ = [
    "AnyOf", "Array", "Boolean", "FieldSpec", "InputFileError", "Invalid", "ListOf", "MAX_BYTES", "MAX_DEPTH",
    "MAX_LINE", "Number", "OutputFileError", "OutputTarget", "String", "Table", "Tagged", "atomic_path", "atomic_write_bytes",
    "atomic_write_text", "atomic_write_with", "check_depth", "check_line_length", "check_output_dir", "check_output_path", "decode_utf8",
    "load_json", "load_toml", "output_target", "parse_json", "parse_toml", "read_bytes", "read_text", "table_from_dataclass",
    "unknown_key_message", "validate",
]
