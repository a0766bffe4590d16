"""Helpers of the robustness tests (`tests/test_robust_*.py`)."""
