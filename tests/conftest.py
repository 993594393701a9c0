import os
import sys

# Test modules share small builders (tests/test_value_expansion.py); make them importable.
sys.path.insert(0, os.path.dirname(__file__))
