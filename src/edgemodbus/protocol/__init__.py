"""Pure bytes and text of the Modbus protocol: RTU frames, wrapped report frames, addresses."""
