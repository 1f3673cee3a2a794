"""The rcan SDK (3.7.0) test cases restated against our public API (docs/conformance.md)."""
