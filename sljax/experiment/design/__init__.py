"""The design of grids: plans by name, what they are made of, and their scales."""
