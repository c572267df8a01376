"""sljax.data: the scene format on disk and in memory, datasets, splits and batches, and the
pre-flight check. Import each name from its module (`from sljax.data.dataset import
FolderSource`): one path per name, which tests/test_imports.py can read."""
