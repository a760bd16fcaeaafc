"""Sortie fdm package (see ARCHITECTURE.md)."""
