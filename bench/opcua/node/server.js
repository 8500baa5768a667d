// node-opcua's server for the OPC UA server benchmark (bench/run): the same
// variables plccoms serves from `loadgen genpub --vars N --animated M`
// under the same names (folder "Bench", STRING NodeIds "Bench.<name>"),
// ANIM_nnnnn UInt32 holding a tick counter that rises every CYCLE ms (as
// plcsim --animate 'ANIM_*' does), every value's SourceTimestamp the time
// it was set; the other variables UInt32 that never change.
//
//     node bench/opcua/node/server.js PORT VARS ANIMATED [CYCLE_MS]
//
// Prints "ready" once it listens. Namespace urn:node-opcua-bench.
"use strict";
const { OPCUAServer, DataType, StatusCodes, Variant } = require("node-opcua");

async function main() {
    const [port, vars, animated] = process.argv.slice(2, 5).map(Number);
    const cycle = Number(process.argv[5] || 100);
    if (!(port > 0 && vars > 0 && animated >= 0 && animated <= vars && cycle > 0)) {
        console.error("usage: server.js PORT VARS ANIMATED [CYCLE_MS]");
        process.exit(2);
    }
    const many = 10 * vars + 1000;
    const server = new OPCUAServer({
        port,
        hostname: "127.0.0.1",
        resourcePath: "/",
        maxConnectionsPerEndpoint: 100,
        // As plccoms' limits (OPCUA_MAX_*): nothing here may refuse the
        // generator's 100,000 items in one session or its 10,000-node Read.
        serverCapabilities: {
            maxBrowseContinuationPoints: 100,
            operationLimits: {
                maxNodesPerRead: many,
                maxNodesPerBrowse: many,
                maxMonitoredItemsPerCall: many,
                maxNodesPerTranslateBrowsePathsToNodeIds: many,
            },
            maxMonitoredItems: many,
            maxMonitoredItemsPerSubscription: many,
            maxSubscriptionsPerSession: 100,
            maxSubscriptions: 1000,
            maxMonitoredItemsQueueSize: 1000,
        },
    });
    await server.initialize();
    const space = server.engine.addressSpace;
    const ns = space.registerNamespace("urn:node-opcua-bench");
    const folder = ns.addFolder(space.rootFolder.objects, { nodeId: "s=Bench", browseName: "Bench" });
    const changing = [];
    for (let i = 0; i < vars; i++) {
        const name = i < animated ? `ANIM_${String(i).padStart(5, "0")}` : `VAR_${String(i - animated).padStart(5, "0")}`;
        const v = ns.addVariable({
            componentOf: folder,
            nodeId: `s=Bench.${name}`,
            browseName: name,
            dataType: "UInt32",
            value: { dataType: DataType.UInt32, value: 0 },
            // Written by bench-opcua's SETs (`--against node`).
            accessLevel: "CurrentRead | CurrentWrite",
            userAccessLevel: "CurrentRead | CurrentWrite",
        });
        if (i < animated) changing.push(v);
    }
    await server.start();
    console.log("ready");
    let tick = 0;
    setInterval(() => {
        tick += 1;
        const now = new Date();
        for (const v of changing) {
            v.setValueFromSource(new Variant({ dataType: DataType.UInt32, value: tick }), StatusCodes.Good, now);
        }
    }, cycle);
    const stop = async () => {
        await server.shutdown(0);
        process.exit(0);
    };
    process.on("SIGTERM", stop);
    process.on("SIGINT", stop);
}

main().catch((e) => {
    console.error(e);
    process.exit(1);
});
