"""The gateway's Modbus TCP server: serve mode and the server side of forward
mode.

* settings.py: the ``serve`` section of the gateway file (:class:`ServeSettings`);
* image.py: a served device's items as a unit's register image, and writes back to items;
* server.py: :class:`ModbusTcpServer`, its thread over the C loop (csrc/emb_serve.c).
"""

from .image import UnitImage
from .server import ModbusTcpServer, write_exception_code
from .settings import ServeSettings, ServeUnit, split_listen, unknown_devices

__all__ = ["ModbusTcpServer", "ServeSettings", "ServeUnit", "UnitImage", "split_listen",
           "unknown_devices", "write_exception_code"]
