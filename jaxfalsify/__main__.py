"""``python -m jaxfalsify ...``: the same as the ``jaxfalsify`` console script."""

from jaxfalsify.cli import entry

if __name__ == "__main__":
    entry()
