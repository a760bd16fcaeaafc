"""Sortie client package (see ARCHITECTURE.md)."""
