"""An OPC UA server (asyncua) whose structures have NO field child nodes,
only a DataTypeDefinition, as TwinCAT's and many S7-1500 UDT instances
show them; and a two-dimensional array. For tests/opcua_struct.rs.

    python3 structs.py PORT

Objects/
  MOTOR    MotorT, writable: SPEED Double, RUNNING Boolean, NAME String,
           STEPS UInt16[3], POS PointT (X Int16, Y Int16), MODE ModeE (enum),
           ID Guid (not served: walked over)
  POINTS   PointT[2], writable
  MATRIX   Int32[2][3], writable
  BAD      BadT: a field of an abstract type (BaseDataType): skipped

Prints "ready" once it listens; stops when stdin closes. Commands on
stdin, one a line, each answered "done" (after any output line):
  speed V   sets MOTOR.SPEED to V (the rest as it is)
  show NAME prints NAME's value (repr)
"""

import asyncio
import sys
import uuid

from asyncua import Server, ua
from asyncua.common.structures104 import new_enum, new_struct, new_struct_field

NS_URI = "http://plccoms.test/structs"


def array_field(name, dtype, n):
    field = new_struct_field(name, dtype, array=True)
    # asyncua writes [1] for every array field: the real length instead.
    field.ArrayDimensions = [n]
    return field


async def main():
    port = int(sys.argv[1])
    server = Server()
    await server.init()
    server.set_endpoint(f"opc.tcp://127.0.0.1:{port}/plc")
    server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
    ns = await server.register_namespace(NS_URI)
    objects = server.nodes.objects

    point_t, _ = await new_struct(
        server, ns, "PointT",
        [new_struct_field("X", ua.VariantType.Int16), new_struct_field("Y", ua.VariantType.Int16)],
    )
    mode_e = await new_enum(server, ns, "ModeE", ["Off", "Auto", "Manual"])
    motor_t, _ = await new_struct(
        server, ns, "MotorT",
        [
            new_struct_field("SPEED", ua.VariantType.Double),
            new_struct_field("RUNNING", ua.VariantType.Boolean),
            new_struct_field("NAME", ua.VariantType.String),
            array_field("STEPS", ua.VariantType.UInt16, 3),
            new_struct_field("POS", point_t),
            new_struct_field("MODE", mode_e),
            new_struct_field("ID", ua.VariantType.Guid),
        ],
    )
    bad_t, _ = await new_struct(
        server, ns, "BadT",
        [new_struct_field("ANY", ua.NodeId(24, 0))],
    )
    await server.load_data_type_definitions()

    motor = await objects.add_variable(
        ua.NodeId("MOTOR", ns), ua.QualifiedName("MOTOR", ns),
        ua.MotorT(
            SPEED=1450.5, RUNNING=True, NAME="Pump", STEPS=[10, 20, 30],
            POS=ua.PointT(X=3, Y=-4), MODE=ua.ModeE.Auto,
            ID=uuid.UUID("72962b91-fa75-4ae6-8d28-b404dc7daf63"),
        ),
        datatype=motor_t.nodeid,
    )
    await motor.set_writable()
    points = await objects.add_variable(
        ua.NodeId("POINTS", ns), ua.QualifiedName("POINTS", ns),
        ua.Variant([ua.PointT(X=1, Y=2), ua.PointT(X=5, Y=6)], ua.VariantType.ExtensionObject),
        datatype=point_t.nodeid,
    )
    await points.write_value_rank(1)
    await points.write_array_dimensions([2])
    await points.set_writable()
    matrix = await objects.add_variable(
        ua.NodeId("MATRIX", ns), ua.QualifiedName("MATRIX", ns),
        ua.Variant([[1, 2, 3], [4, 5, 6]], ua.VariantType.Int32, Dimensions=[2, 3]),
    )
    await matrix.write_value_rank(2)
    await matrix.write_array_dimensions([2, 3])
    await matrix.set_writable()
    await objects.add_variable(
        ua.NodeId("BAD", ns), ua.QualifiedName("BAD", ns),
        ua.Variant(None, ua.VariantType.Null), datatype=bad_t.nodeid,
    )
    nodes = {"MOTOR": motor, "POINTS": points, "MATRIX": matrix}

    async with server:
        print("ready", flush=True)
        loop = asyncio.get_running_loop()
        while True:
            line = await loop.run_in_executor(None, sys.stdin.readline)
            if not line:
                # The test is gone (stdin closed): so is the server.
                break
            words = line.split()
            if words[:1] == ["speed"]:
                value = await motor.read_value()
                value.SPEED = float(words[1])
                await motor.write_value(ua.Variant(value, ua.VariantType.ExtensionObject))
            elif words[:1] == ["show"]:
                print(repr(await nodes[words[1]].read_value()), flush=True)
            print("done", flush=True)


asyncio.run(main())
