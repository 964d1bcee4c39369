"""Integration tests: real wire I/O against independent peers (see tests/peers.py)."""
