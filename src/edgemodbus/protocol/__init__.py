"""Modbus on the wire as pure bytes and text: framing facts shared by the master's links,
the DTU listener and the simulator (rtu.py: CRC-16, RTU frames, function codes, frame
lengths and splitting; wrapped.py: the wrapped report frame; address.py: item addresses).
Nothing here does I/O or keeps state, so every layer may import it; the package itself
imports nothing, import its modules directly.
"""
