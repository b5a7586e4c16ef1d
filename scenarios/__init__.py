"""The packaged scenarios: this folder's ``*.toml`` files, shipped in the wheel as package data.

No code here; ``services.model.catalog`` finds the files by name through
``importlib.resources`` (see ``README.md`` in this folder, "Packaged scenarios").
"""
