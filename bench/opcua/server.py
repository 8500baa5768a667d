"""A local OPC UA server for the OPC UA client benchmark (issue 31): N
Double variables under Objects/BULK, a tenth of them changed every second
(asyncua, PyPI; the same server the tests use).

    python3 bench/opcua/server.py PORT N

Prints "ready" once it listens (10,000 variables: about 30 s to build;
100,000: minutes). The section under test:

    [*]
    COMM_LOOP_DELAY = 1000
    [B]
    PROTOCOL       = OPCUA
    OPCUA_URL      = opc.tcp://127.0.0.1:PORT/bench
    OPCUA_BROWSE   = ns=2;s=BULK
    OPCUA_REBROWSE = 0
    SERVER_PORT    = ...

then one client sends EN: and reads DIFFs; plccoms's RSS and CPU time are
taken from /proc over a steady window (the issue's goals: 100,000 at 1 s in
<= 128 MiB and <= 0.3 core). For SET -> confirmed DIFF, a second client
sends SET:BULK.V0,<n> and times the DIFF that confirms it (goal p99 <=
10 ms). Run it with a release build; the server is Python and takes a core
of its own at 100,000 variables, so pin it apart (taskset) and say so.
"""

import asyncio
import sys

from asyncua import Server, ua


async def main():
    port, n = int(sys.argv[1]), int(sys.argv[2])
    server = Server()
    await server.init()
    server.set_endpoint(f"opc.tcp://127.0.0.1:{port}/bench")
    server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
    ns = await server.register_namespace("http://plccoms.bench/opcua")
    folder = await server.nodes.objects.add_folder(ua.NodeId("BULK", ns), ua.QualifiedName("BULK", ns))
    nodes = []
    for i in range(n):
        node = await folder.add_variable(ua.NodeId(f"V{i}", ns), ua.QualifiedName(f"V{i}", ns), float(i))
        await node.set_writable()
        nodes.append(node.nodeid)
    async with server:
        print("ready", flush=True)
        tick = 0
        while True:
            await asyncio.sleep(1)
            tick += 1
            for i in range(tick % 10, n, 10):
                await server.write_attribute_value(nodes[i], ua.DataValue(float(i + tick)))


asyncio.run(main())
