"""The package's version: one place, imported by the root package and by what records it (no other import)."""

__version__ = "0.1.0"
