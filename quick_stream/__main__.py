"""``python -m quick_stream`` = the ``quick-stream`` command."""
import sys

from .cli import main

sys.exit(main())
