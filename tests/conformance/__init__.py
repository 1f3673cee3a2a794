"""Conformance suites: other implementations' own test cases, restated against ours."""
