"""`python -m lab ...` (from the repository's root): see lab/cli.py."""
import sys

from .cli import main

sys.exit(main())
