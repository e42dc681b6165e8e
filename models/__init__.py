"""MJCF scenes shipped with mjstamp (data, loaded with importlib.resources)."""
