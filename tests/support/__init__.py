"""Test and script support code that is not part of the library (one module per side)."""
