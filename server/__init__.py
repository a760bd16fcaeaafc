"""Sortie server package (see ARCHITECTURE.md)."""
