"""The version of flexmbs (recorded in fingerprints and reports)."""
__version__ = "0.1.0"
