"""Importers: convert recorded datasets from other formats into the swarmnav dataset format."""
