"""Bytes on disk and in memory: files written whole, images and their headers, sizes, pictures,
Markdown tables."""
