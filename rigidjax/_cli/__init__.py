"""The ``rigidjax`` command line, built on the public rigidjax functions only.

- ``rigidjax simulate`` (``simulate.py``, scenes in ``scenes.py``): batch-simulate a scene of many
  bodies; write an ``.npz`` and a figure.
- ``rigidjax fit data.csv`` (``fit.py``): fit a body's inertia to a gyroscope record.
- ``rigidjax bench`` (``bench.py``): time and error of each accuracy setting of ``simulate``.

``parser.py`` holds the parser and :func:`main`; ``common.py`` the argument types and progress lines.
"""

from .parser import build_parser as build_parser
from .parser import main as main

__all__ = ["build_parser", "main"]
