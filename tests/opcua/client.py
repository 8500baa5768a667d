"""An OPC UA client for tests/opcua.rs: asyncua (FreeOpcUa's Python
stack), a third-party implementation, driven by the tests. Each command
prints JSON lines on stdout; a failure to connect prints
{"error": "<status name or message>"} and exits 2.

  client.py browse URL                       the tree under plccoms, every variable read
  client.py write URL NODE TYPE VALUE        one Write; prints its StatusCode's name
  client.py subscribe URL NODE KIND DEADBAND SECONDS [PUBLISH_MS QUEUE SAMPLING_MS MODIFY_MS]
                                             one monitored item (KIND none, absolute,
                                             percent; publishing every 20 ms, a queue
                                             of 1000 and sampling 0 unless given; with
                                             MODIFY_MS, then modified to sample so); prints
                                             "ready", then each value (with "overflow":
                                             the StatusCode's Overflow bit, 0x80)
  client.py history URL NODE FROM_MS TO_MS PER_PAGE
                                             HistoryRead raw, page by page (--bounds:
                                             with ReturnBounds)
  client.py hold URL NODE                    subscribes and waits forever (to be killed)
  client.py paths URL SECTION VARIABLE PAGE  TranslateBrowsePaths, and Browse with BrowseNext
  client.py attrs URL NODE                   every attribute of NODE and of its properties,
                                             with their references
  client.py events URL SECONDS               GeneralModelChangeEvents of the Server object
  client.py --cert DIR makecert -            only makes the client's certificate

Options before the command: --user NAME --password PW, --security
"Basic256Sha256,SignAndEncrypt" with --cert DIR (a certificate made there
on first use).
"""

import argparse
import asyncio
import datetime
import enum
import json
import socket
import sys

from asyncua import Client, ua


def out(obj):
    print(json.dumps(obj, default=str), flush=True)


def status_name(code):
    try:
        return ua.StatusCode(code.value if hasattr(code, "value") else code).name
    except Exception:
        return str(code)


def plain(value):
    if isinstance(value, datetime.datetime):
        if value.tzinfo is None:
            value = value.replace(tzinfo=datetime.timezone.utc)
        return value.isoformat()
    if hasattr(value, "Low") and hasattr(value, "High"):
        return {"low": value.Low, "high": value.High}
    if hasattr(value, "DisplayName") and hasattr(value, "UnitId"):
        return {"unit": value.DisplayName.Text}
    return value


async def make_cert(folder):
    """The client's certificate and key in `folder` (made once): its
    application URI, and the two paths."""
    from pathlib import Path

    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    key, cert = folder / "key.pem", folder / "cert.der"
    uri = "urn:plccoms-tests:asyncua"
    if not cert.exists():
        await setup_self_signed_certificate(
            key, cert, uri, socket.gethostname(),
            [ExtendedKeyUsageOID.CLIENT_AUTH], {"commonName": "plccoms tests"},
        )
    return uri, cert, key


async def connect(args):
    # The liveness probe every 10 s, not asyncua's 1 s: a Read of
    # ServerState that waits over 1 s behind thousands of notifications a
    # second in this Python process (two busy cores) dropped the connection
    # and every change after it.
    client = Client(url=args.url, timeout=10, watchdog_intervall=10)
    if args.user:
        client.set_user(args.user)
        client.set_password(args.password or "")
    if args.security:
        uri, cert, key = await make_cert(args.cert)
        client.application_uri = uri
        await client.set_security_string(f"{args.security},{cert},{key}")
    await client.connect()
    return client


async def browse(client, args):
    ns = await client.get_namespace_index("urn:plccoms")
    root = client.get_node(ua.NodeId("plccoms", ns))
    for section in await root.get_children():
        sname = (await section.read_browse_name()).Name
        for child in await section.get_children():
            item = {"section": sname, "name": (await child.read_browse_name()).Name,
                    "id": child.nodeid.Identifier}
            if await child.read_node_class() == ua.NodeClass.Variable:
                dtype = await child.read_data_type()
                item["type"] = (await client.get_node(dtype).read_browse_name()).Name
                dv = await child.read_data_value(raise_on_bad_status=False)
                item["value"] = plain(dv.Value.Value) if dv.Value is not None else None
                item["variant"] = dv.Value.VariantType.name if dv.Value is not None else None
                item["status"] = status_name(dv.StatusCode)
                item["source_ts"] = plain(dv.SourceTimestamp)
                item["access"] = await child.read_attribute(ua.AttributeIds.AccessLevel)
                item["access"] = item["access"].Value.Value
                item["historizing"] = (await child.read_attribute(ua.AttributeIds.Historizing)).Value.Value
                desc = (await child.read_attributes([ua.AttributeIds.Description]))[0]
                text = desc.Value.Value if desc.StatusCode.is_good() and desc.Value else None
                item["description"] = text.Text if text is not None else None
                for prop in await child.get_properties():
                    pname = (await prop.read_browse_name()).Name
                    item[pname] = plain(await prop.read_value())
            out(item)


TYPES = {
    "Boolean": lambda v: v.lower() == "true",
    "SByte": int, "Byte": int, "Int16": int, "UInt16": int, "Int32": int,
    "UInt32": int, "Int64": int, "UInt64": int, "Float": float, "Double": float,
    "String": str,
    "DateTime": lambda v: datetime.datetime.fromisoformat(v),
}


async def write(client, args):
    ns = await client.get_namespace_index("urn:plccoms")
    node = client.get_node(ua.NodeId(args.node, ns))
    variant = ua.Variant(TYPES[args.type](args.value), getattr(ua.VariantType, args.type))
    params = ua.WriteParameters()
    params.NodesToWrite = [ua.WriteValue(NodeId=node.nodeid, AttributeId=ua.AttributeIds.Value,
                                         Value=ua.DataValue(variant))]
    results = await client.uaclient.write_value(params) if hasattr(client.uaclient, "write_value") \
        else await client.uaclient.write(params)
    out({"status": status_name(results[0])})


async def drain(queue, seconds):
    """Prints what comes on `queue` for `seconds`, then {"done": true}."""
    deadline = asyncio.get_running_loop().time() + seconds
    while True:
        left = deadline - asyncio.get_running_loop().time()
        if left <= 0:
            break
        try:
            out(await asyncio.wait_for(queue.get(), timeout=left))
        except asyncio.TimeoutError:
            break
    out({"done": True})


class Handler:
    def __init__(self):
        self.values = asyncio.Queue()

    def datachange_notification(self, node, val, data):
        dv = data.monitored_item.Value
        code = dv.StatusCode.value
        # The name of the code (its upper 16 bits), and the Overflow bit
        # (0x80; async-opcua 0.19 sets it without InfoType DataValue, 0x400).
        self.values.put_nowait({"value": plain(val), "status": status_name(code & 0xFFFF0000),
                                "overflow": bool(code & 0x80),
                                "source_ts": plain(dv.SourceTimestamp)})


async def subscribe(client, args):
    ns = await client.get_namespace_index("urn:plccoms")
    node = client.get_node(ua.NodeId(args.node, ns))
    handler = Handler()
    sub = await client.create_subscription(int(getattr(args, "publish_ms", 20)), handler)
    kind = {"none": 0, "absolute": 1, "percent": 2}[args.kind]
    params = ua.MonitoringParameters()
    params.ClientHandle = 1
    params.SamplingInterval = float(getattr(args, "sampling_ms", 0))
    params.QueueSize = int(getattr(args, "queue", 1000))
    params.DiscardOldest = True
    if kind:
        flt = ua.DataChangeFilter()
        flt.Trigger = ua.DataChangeTrigger.StatusValue
        flt.DeadbandType = kind
        flt.DeadbandValue = float(args.deadband)
        params.Filter = flt
    request = ua.MonitoredItemCreateRequest()
    request.ItemToMonitor.NodeId = node.nodeid
    request.ItemToMonitor.AttributeId = ua.AttributeIds.Value
    request.MonitoringMode = ua.MonitoringMode.Reporting
    request.RequestedParameters = params
    # Through asyncua's own bookkeeping (so notifications reach the
    # handler), keeping the server's answer for its revised parameters.
    answers = {}
    create = sub.server.create_monitored_items

    async def keep(params):
        answers["results"] = await create(params)
        return answers["results"]

    sub.server.create_monitored_items = keep
    await sub.create_monitored_items([request])
    result = answers["results"][0]
    revised_sampling = result.RevisedSamplingInterval
    if getattr(args, "modify_ms", None) is not None:
        modified = await sub.modify_monitored_item(
            result.MonitoredItemId, float(args.modify_ms), params.QueueSize)
        revised_sampling = modified[0].RevisedSamplingInterval
    out({"ready": True, "status": status_name(result.StatusCode),
         # asyncua keeps the server's revised interval in its parameters.
         "revised_publishing": sub.parameters.RequestedPublishingInterval,
         "revised_sampling": revised_sampling,
         "revised_queue": result.RevisedQueueSize})
    await drain(handler.values, float(args.seconds))


async def history(client, args):
    ns = await client.get_namespace_index("urn:plccoms")
    node_id = ua.NodeId(args.node, ns)
    details = ua.ReadRawModifiedDetails()
    details.IsReadModified = False
    details.StartTime = datetime.datetime.fromtimestamp(int(args.from_ms) / 1000, datetime.timezone.utc)
    details.EndTime = datetime.datetime.fromtimestamp(int(args.to_ms) / 1000, datetime.timezone.utc)
    details.NumValuesPerNode = int(args.per_page)
    details.ReturnBounds = bool(args.bounds)
    point = None
    pages = 0
    while True:
        params = ua.HistoryReadParameters()
        params.HistoryReadDetails = details
        params.TimestampsToReturn = ua.TimestampsToReturn.Both
        params.ReleaseContinuationPoints = False
        rv = ua.HistoryReadValueId()
        rv.NodeId = node_id
        rv.ContinuationPoint = point
        params.NodesToRead = [rv]
        result = (await client.uaclient.history_read(params))[0]
        pages += 1
        values = result.HistoryData.DataValues if result.HistoryData is not None else []
        out({"page": pages, "status": status_name(result.StatusCode),
             "values": [{"value": plain(dv.Value.Value) if dv.Value is not None else None,
                         "status": status_name(dv.StatusCode),
                         "ts": plain(dv.SourceTimestamp)} for dv in (values or [])],
             "more": bool(result.ContinuationPoint)})
        point = result.ContinuationPoint
        if not point:
            break


class EventHandler:
    def __init__(self):
        self.events = asyncio.Queue()

    def event_notification(self, event):
        self.events.put_nowait({"event_type": str(event.EventType),
                                "source": getattr(event, "SourceName", None),
                                "message": event.Message.Text if event.Message else None})


async def events(client, args):
    handler = EventHandler()
    sub = await client.create_subscription(20, handler)
    server = client.get_node(ua.ObjectIds.Server)
    # Every event of the Server object (BaseEventType), as most clients
    # subscribe; the test checks the type.
    # A queue for every event of a burst (a reload raises several at once).
    await sub.subscribe_events(server, queuesize=1000)
    out({"ready": True})
    await drain(handler.events, float(args.seconds))


async def paths(client, args):
    """TranslateBrowsePathsToNodeIds of plccoms/<section>/<variable>, and
    Browse of the section PAGE references at a time, with BrowseNext."""
    ns = await client.get_namespace_index("urn:plccoms")
    objects = client.get_node(ua.ObjectIds.ObjectsFolder)
    node = await objects.get_child([f"{ns}:plccoms", f"{ns}:{args.section}", f"{ns}:{args.variable}"])
    out({"translated": node.nodeid.Identifier})
    desc = ua.BrowseDescription()
    desc.NodeId = ua.NodeId(args.section, ns)
    desc.BrowseDirection = ua.BrowseDirection.Forward
    desc.ReferenceTypeId = ua.NodeId(ua.ObjectIds.HierarchicalReferences)
    desc.IncludeSubtypes = True
    desc.ResultMask = ua.BrowseResultMask.All
    params = ua.BrowseParameters()
    params.View.Timestamp = ua.get_win_epoch()  # as asyncua's own browse: no view
    params.NodesToBrowse = [desc]
    params.RequestedMaxReferencesPerNode = int(args.page)
    result = (await client.uaclient.browse(params))[0]
    names = [r.BrowseName.Name for r in result.References]
    statuses = {status_name(result.StatusCode)}
    most = len(result.References)
    calls = 1
    while result.ContinuationPoint:
        more = ua.BrowseNextParameters()
        more.ReleaseContinuationPoints = False
        more.ContinuationPoints = [result.ContinuationPoint]
        result = (await client.uaclient.browse_next(more))[0]
        names += [r.BrowseName.Name for r in result.References]
        statuses.add(status_name(result.StatusCode))
        most = max(most, len(result.References))
        calls += 1
    out({"names": names, "calls": calls, "statuses": sorted(statuses), "most": most})


def attribute_values(results):
    """Each attribute read, by name: its value, or its StatusCode's name."""
    got = {}
    for attr, dv in zip(ua.AttributeIds, results):
        if dv.StatusCode.is_good():
            got[attr.name] = plain_attr(dv.Value.Value)
        else:
            got[attr.name] = status_name(dv.StatusCode)
    return got


def plain_attr(value):
    if isinstance(value, ua.NodeId):
        return value.to_string()
    if isinstance(value, ua.QualifiedName):
        return f"{value.NamespaceIndex}:{value.Name}"
    if isinstance(value, ua.LocalizedText):
        return value.Text
    if isinstance(value, enum.Enum):
        return value.value
    return plain(value)


async def node_refs(node):
    refs = await node.get_references(refs=ua.ObjectIds.References,
                                     direction=ua.BrowseDirection.Both)
    return sorted(
        [{"type": r.ReferenceTypeId.to_string(), "forward": r.IsForward,
          "node": r.NodeId.to_string(), "name": f"{r.BrowseName.NamespaceIndex}:{r.BrowseName.Name}",
          "class": r.NodeClass.value, "type_def": r.TypeDefinition.to_string()} for r in refs],
        key=lambda r: (r["type"], r["node"]))


async def attrs(client, args):
    """Every attribute (1..27) of NODE and of each of its properties, with
    the references of each (both directions)."""
    ns = await client.get_namespace_index("urn:plccoms")
    node = client.get_node(ua.NodeId(args.node, ns))
    properties = await node.get_properties()
    for n in [node] + properties:
        results = await n.read_attributes(list(ua.AttributeIds))
        out({"node": n.nodeid.Identifier, "attrs": attribute_values(results),
             "refs": await node_refs(n)})
    # TranslateBrowsePaths from the variable to each property and back.
    for p in properties:
        name = (await p.read_browse_name()).Name
        there = await node.get_child([f"0:{name}"])
        path = ua.BrowsePath()
        path.StartingNode = there.nodeid
        element = ua.RelativePathElement()
        element.ReferenceTypeId = ua.NodeId(ua.ObjectIds.HasProperty)
        element.IsInverse = True
        element.TargetName = ua.QualifiedName(args.node.split(".", 1)[1], ns)
        path.RelativePath.Elements = [element]
        result = (await client.uaclient.translate_browsepaths_to_nodeids([path]))[0]
        back = [t.TargetId.Identifier for t in result.Targets]
        out({"translated": there.nodeid.Identifier, "back": back})


async def hold(client, args):
    ns = await client.get_namespace_index("urn:plccoms")
    node = client.get_node(ua.NodeId(args.node, ns))
    handler = Handler()
    sub = await client.create_subscription(20, handler)
    await sub.subscribe_data_change(node)
    out({"ready": True})
    while True:
        item = await handler.values.get()
        out(item)


async def read(client, args):
    ns = await client.get_namespace_index("urn:plccoms")
    dv = await client.get_node(ua.NodeId(args.node, ns)).read_data_value(
        raise_on_bad_status=False)
    out({"status": status_name(dv.StatusCode),
         "value": plain(dv.Value.Value) if dv.Value is not None else None})


class NodeHandler:
    def __init__(self):
        self.values = asyncio.Queue()

    def datachange_notification(self, node, val, data):
        dv = data.monitored_item.Value
        self.values.put_nowait({"node": node.nodeid.Identifier, "value": plain(val),
                                "status": status_name(dv.StatusCode)})


async def watch(client, args):
    """Every change of value or status of the comma-separated nodes, one
    line each, until killed."""
    ns = await client.get_namespace_index("urn:plccoms")
    handler = NodeHandler()
    sub = await client.create_subscription(20, handler)
    flt = ua.DataChangeFilter()
    flt.Trigger = ua.DataChangeTrigger.StatusValue
    nodes = [client.get_node(ua.NodeId(n, ns)) for n in args.nodes.split(",")]
    # Deadband none with trigger StatusValue: status-only changes too
    # (subscribe_data_change takes no filter).
    results = await sub._subscribe(nodes, mfilter=flt, queuesize=1000)
    out({"ready": True, "created": [isinstance(r, int) for r in results]})
    while True:
        item = await handler.values.get()
        out(item)


async def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--user")
    parser.add_argument("--password")
    parser.add_argument("--security")
    parser.add_argument("--cert")
    parser.add_argument("--bounds", action="store_true")
    parser.add_argument("command")
    parser.add_argument("url")
    parser.add_argument("rest", nargs="*")
    args = parser.parse_args()
    names = {
        "browse": [], "write": ["node", "type", "value"],
        "subscribe": ["node", "kind", "deadband", "seconds", "publish_ms", "queue", "sampling_ms",
                      "modify_ms"],
        "history": ["node", "from_ms", "to_ms", "per_page"], "hold": ["node"],
        "makecert": [], "events": ["seconds"], "watch": ["nodes"], "read": ["node"], "paths": ["section", "variable", "page"],
        "attrs": ["node"],
    }[args.command]
    for name, value in zip(names, args.rest):
        setattr(args, name, value)
    if args.command == "makecert":
        await make_cert(args.cert)
        out({"made": True})
        return
    try:
        client = await connect(args)
    except ua.UaStatusCodeError as e:
        out({"error": status_name(e.code)})
        sys.exit(2)
    except Exception as e:  # refused before a status: the channel
        out({"error": f"{type(e).__name__}: {e}"})
        sys.exit(2)
    try:
        await globals()[args.command](client, args)
    finally:
        try:
            await client.disconnect()
        except Exception:
            pass


if __name__ == "__main__":
    asyncio.run(main())
