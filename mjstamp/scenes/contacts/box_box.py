"""Ports of MuJoCo C's colliders: box_box (stub; being ported)."""
