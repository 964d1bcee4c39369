"""Test suite of edgemodbus (a package so that `from tests.peers import ...` works)."""
