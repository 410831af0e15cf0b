"""The package version: the one place it is written (pyproject.toml reads it from here).

A literal rather than ``importlib.metadata.version("nlpsf")``: that lookup imports the email
parser and scans the installed distributions, about 25 ms on every CLI start, and every output
carries the version in its conditions.
"""

__version__ = "0.1.0"
