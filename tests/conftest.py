"""Shared test helpers. The virtual clock comes from asyncdonkey's own pytest plugin (entry point)."""
