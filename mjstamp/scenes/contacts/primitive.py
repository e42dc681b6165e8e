"""Ports of MuJoCo C's primitive colliders (engine_collision_primitive.c)."""
