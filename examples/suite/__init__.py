"""A suite of user-style MJCF scenes and tasks (issue 10, part 6); see tasks.py."""
