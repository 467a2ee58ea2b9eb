"""``python -m fastsdf``: the command line of :mod:`fastsdf.apps.cli`."""

from fastsdf.apps.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
