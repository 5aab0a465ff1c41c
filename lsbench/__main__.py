"""`python -m lsbench` is the `lsbench` command."""
import sys

from lsbench.cli import main

sys.exit(main())
