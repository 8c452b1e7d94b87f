"""Meshes and their looks, BVHs, traversal, exact ray queries, compact meshes, bundled and generated assets."""
