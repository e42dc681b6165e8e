"""Ports of MuJoCo C's colliders: capsule_box (stub; being ported)."""
