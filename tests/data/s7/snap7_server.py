"""An S7 server for the tests: python-snap7's (3.x: pure Python; 1.x: the
Snap7 C library in its wheel), serving the areas given as JSON:

    {"port": 1102, "areas": [["DB", 1, "<hex>"], ["MK", 0, "<hex>"], ...]}

(a number in place of the hex: that many zero bytes).

Prints "ready" once it listens. Commands on stdin, one a line:
    stop | run                         the CPU's mode (SZL 0x0424)
    peek <AREA> <index> <start> <len>  prints "peek <hex>"
    poke <AREA> <index> <start> <hex>  prints "poked"
"""

import ctypes
import json
import sys

import snap7
import snap7.server

config = json.loads(sys.argv[1])
legacy = snap7.__version__.startswith("1.")
if legacy:
    from snap7 import types as t

    codes = {"PE": t.srvAreaPE, "PA": t.srvAreaPA, "MK": t.srvAreaMK, "DB": t.srvAreaDB}
else:
    from snap7.type import SrvArea

    codes = {"PE": SrvArea.PE, "PA": SrvArea.PA, "MK": SrvArea.MK, "DB": SrvArea.DB}

server = snap7.server.Server(log=False)
memory = {}
for area, index, data in config["areas"]:
    data = bytes(data) if isinstance(data, int) else bytes.fromhex(data)
    if legacy:
        buffer = (ctypes.c_uint8 * len(data)).from_buffer_copy(data)
    else:
        buffer = bytearray(data)
    memory[(area, int(index))] = buffer
    server.register_area(codes[area], int(index), buffer)

if legacy:
    server.start(tcpport=config["port"])
else:
    server.start(tcp_port=config["port"])
print("ready", snap7.__version__, flush=True)

for line in sys.stdin:
    words = line.split()
    if not words:
        continue
    if words[0] in ("stop", "run"):
        server.set_cpu_status(4 if words[0] == "stop" else 8)
        print("ok", flush=True)
    elif words[0] == "peek":
        buffer = memory[(words[1], int(words[2]))]
        start, length = int(words[3]), int(words[4])
        print("peek", bytes(buffer[start : start + length]).hex(), flush=True)
    elif words[0] == "poke":
        buffer = memory[(words[1], int(words[2]))]
        start, data = int(words[3]), bytes.fromhex(words[4])
        for i, b in enumerate(data):
            buffer[start + i] = b
        print("poked", flush=True)
