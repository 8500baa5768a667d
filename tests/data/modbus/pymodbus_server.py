"""A Modbus TCP device for plccoms' tests: pymodbus's server with the
register image the test gives it (JSON on the command line), every address
outside it invalid (answered with exception 2).

    python3 pymodbus_server.py '{"port": 15020, "holding": {"0": [1, 2]}, ...}'

Tables: "coils" and "discrete" (lists of 0/1), "holding" and "input" (lists of
16-bit registers), each a map from the first address of a block to its values
(an empty table holds its last address only).
Prints "ready <port>" once it listens; stops on SIGTERM.
"""

import asyncio
import json
import sys

from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice


def blocks(table, bits):
    if not table:
        # pymodbus wants a block in every table: the last address.
        table = {"65535": [0]}
    return [
        SimData(
            int(address),
            values=[bool(v) for v in values] if bits else list(values),
            datatype=DataType.BITS if bits else DataType.REGISTERS,
        )
        for address, values in sorted(table.items(), key=lambda kv: int(kv[0]))
    ]


async def main():
    image = json.loads(sys.argv[1])
    device = SimDevice(
        id=0,
        simdata=(
            blocks(image.get("coils", {}), True),
            blocks(image.get("discrete", {}), True),
            blocks(image.get("holding", {}), False),
            blocks(image.get("input", {}), False),
        ),
    )
    server = ModbusTcpServer(device, address=("127.0.0.1", image["port"]))
    task = asyncio.create_task(server.serve_forever())
    # serve_forever binds before it serves; wait until the port answers.
    for _ in range(200):
        try:
            _, writer = await asyncio.open_connection("127.0.0.1", image["port"])
            writer.close()
            break
        except OSError:
            await asyncio.sleep(0.05)
    print(f"ready {image['port']}", flush=True)
    await task


asyncio.run(main())
