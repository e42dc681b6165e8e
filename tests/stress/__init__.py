"""Stress tests the tests run: fuzzed scenes and command lines, kill -9 and resume."""
