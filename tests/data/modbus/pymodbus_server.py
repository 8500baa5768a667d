"""A Modbus TCP device for plccoms' tests: pymodbus's server with the
register image the test gives it (JSON on the command line), every address
outside it invalid (answered with exception 2).

    python3 pymodbus_server.py '{"port": 15020, "holding": {"0": [1, 2]}, ...}'

Tables: "coils" and "discrete" (lists of 0/1), "holding" and "input" (lists of
16-bit registers), each a map from the first address of a block to its values
(an empty table holds its last address only).
Prints "ready <port>" once it listens; stops on SIGTERM.

Modbus RTU: "serial": a tty (one end of a pty pair) to serve RTU on, or
"rtu": true to serve RTU frames over TCP on "port"; "units": a map from unit
id to that unit's tables, the units not in it staying silent, as absent
devices on a line do (pymodbus would answer them with exception 4 unless
told to ignore them). Prints "connect" for each TCP connection.
"""

import asyncio
import json
import sys

from pymodbus import FramerType
from pymodbus.exceptions import NoSuchIdException
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice, simcore


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


def device(unit, image):
    return SimDevice(
        id=unit,
        simdata=(
            blocks(image.get("coils", {}), True),
            blocks(image.get("discrete", {}), True),
            blocks(image.get("holding", {}), False),
            blocks(image.get("input", {}), False),
        ),
    )


def only_own_units():
    """Makes a unit not in "units" unknown: SimCore otherwise answers it as
    unit 0, and without one with exception 4. Unknown, it stays silent
    (ignore_missing_devices), as an absent device on a line."""

    def get_device(self, device_id):
        if device_id not in self.devices:
            raise NoSuchIdException(f"unit {device_id} is not on this line")
        return self.devices[device_id]

    simcore.SimCore._SimCore__get_device = get_device


# Connections are counted once "ready" is out (not the readiness check).
serving = False


def connected(up):
    if up and serving:
        print("connect", flush=True)


async def main():
    image = json.loads(sys.argv[1])
    units = image.get("units")
    if units is not None:
        only_own_units()
    devices = (
        [device(int(unit), tables) for unit, tables in units.items()]
        if units is not None
        else device(0, image)
    )
    if "serial" in image:
        server = ModbusSerialServer(
            devices,
            framer=FramerType.RTU,
            port=image["serial"],
            baudrate=115200,
            ignore_missing_devices=True,
            broadcast_enable=True,
        )
        task = asyncio.create_task(server.serve_forever())
        await asyncio.sleep(0.5)
        print(f"ready {image['serial']}", flush=True)
        await task
        return
    server = ModbusTcpServer(
        devices,
        framer=FramerType.RTU if image.get("rtu") else FramerType.SOCKET,
        address=("127.0.0.1", image["port"]),
        ignore_missing_devices=units is not None,
        trace_connect=connected,
    )
    task = asyncio.create_task(server.serve_forever())
    # serve_forever binds before it serves; wait until the port answers.
    for _ in range(200):
        try:
            _, writer = await asyncio.open_connection("127.0.0.1", image["port"])
            writer.close()
            break
        except OSError:
            await asyncio.sleep(0.05)
    await asyncio.sleep(0.2)
    global serving
    serving = True
    print(f"ready {image['port']}", flush=True)
    await task


asyncio.run(main())
