"""Running grids: the resumable runner, workers sharing a folder by claims and leases, their
submission, and where a grid stands."""
