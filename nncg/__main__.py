"""`python -m nncg` is `nncg-onnx`."""

import sys

from .cli import main

sys.exit(main())
