import os
import sys

# the package is installed editable (scripts/setup_venv.sh); the tests' own helpers live beside them
sys.path.insert(0, os.path.dirname(__file__))
