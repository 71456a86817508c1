"""Pipelines that tie sources, store, registration and pose graph together (build)."""
