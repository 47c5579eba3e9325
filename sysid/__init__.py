"""Model identification: check the car model against drive logs, diagnose and fit corrections.

Modules: ``log`` (CSV format, readers), ``data`` (preprocessing to uniform segments), ``model``
(multi-step predictors), ``diagnose`` (candidates, significance, forward selection),
``sparse`` (STLSQ), ``report`` (Markdown/PNG/JSON), ``generate`` (synthetic logs).
Method and formats: docs/sysid.md.
"""
