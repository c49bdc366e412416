"""Peers used only in benchmarks (install with ``pip install -e ".[peers]"``); tests never need them."""
