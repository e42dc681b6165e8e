"""Studies of what a solve finds: particles, robustness, the scene suite."""
