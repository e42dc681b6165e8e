"""Ports of MuJoCo C's colliders: convex (stub; being ported)."""
