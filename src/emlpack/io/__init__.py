"""Readers and writers for external file formats."""
