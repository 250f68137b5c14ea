import os
import sys

# the tests run from a checkout as well as from an installed package
sys.path.insert(0, os.path.abspath(os.path.join(os.path.dirname(__file__), "..")))
