"""An OPC UA server modelled on a small S7-1500 (asyncua, a third-party
stack), for tests/opcua_client.rs.

    python3 server.py PORT [--user USER:PASSWORD] [--secure DIR] [--max-sessions N]

--secure: SignAndEncrypt with Basic256Sha256 only, the server's certificate
made in DIR/server, and a client certificate for plccoms made in
DIR/client-pki (own/cert.der, private/private.pem), so the test need not
wait for a key pair made by a debug build. --max-sessions: more sessions
than N are refused (BadMaxConnectionsReached at ActivateSession).

As an S7-1500's server does, it refuses a client's write of a value with a
SourceTimestamp or ServerTimestamp (BadWriteNotSupported).

Objects/
  DB_LINE1/MOTOR/  SPEED (Double, rw), RUNNING (Boolean, rw), COUNT (UInt32, ro)
  TYPES/           one writable variable of every scalar type plccoms serves
  ARRAY_V          Int16[3], writable (served as ARRAY_V[0] .. ARRAY_V[2])
  RECIPE           a structure (RecipeT: TEMP Double, TIME UInt32) whose fields
                   are child variables too, as an S7-1500 shows a UDT
  EMPTY/SUB/       a folder tree without variables

Prints "ready" once it listens; stops when stdin closes. Commands on
stdin, one a line:
  add NAME   adds a Double variable NAME (= 1.5) to DB_LINE1/MOTOR
  addto PARENT NAME  adds a Double variable NAME (= 1.5) as a child of
             variable PARENT (RECIPE, or one of MOTOR's or TYPES')
  browsed    answers `browsed ID ...`: the string node ids of this
             namespace that clients browsed since the last `browsed`
  remove NAME  deletes variable NAME (one added or MOTOR's)
  set NAME V sets TYPES or MOTOR variable NAME to the number V
  slow MS    answers every Read MS milliseconds late (0: at once again)
  slowbrowse MS  answers every Browse MS milliseconds late (0: at once again)
  stamp NAME V MS  sets NAME to V with SourceTimestamp MS (Unix ms)
  status NAME uncertain|good [V]  sets NAME's StatusCode (UncertainLastUsableValue
                   or Good), its value to V if given, SourceTimestamp now
  wrote      answers `wrote apart` when every Write so far came on a session
             without subscriptions, `wrote together` when every one came on
             a session with one, else `wrote mixed` (or `wrote nothing`)
  items      answers `items N1 N2 ...`: the monitored items created on each
             session that made any (of its client's, in the order the
             sessions began), or `items` when none
"""

import asyncio
import datetime
import sys

from asyncua import Server, ua
from asyncua.common.structures104 import new_struct, new_struct_field
from asyncua.server.user_managers import UserManager
from asyncua.crypto.permission_rules import User, UserRole
from asyncua.server.internal_session import InternalSession

NS_URI = "http://plccoms.test/s7like"

# A slow server: every Read waits this long (seconds) before it is answered.
READ_DELAY = [0.0]
_read = InternalSession.read


async def _slow_read(self, params):
    if READ_DELAY[0]:
        await asyncio.sleep(READ_DELAY[0])
    return await _read(self, params)


InternalSession.read = _slow_read

# A server slow to browse (a PLC's large address space): every Browse waits
# this long (seconds).
BROWSE_DELAY = [0.0]
_browse = InternalSession.browse


# The nodes of this server's namespace a client browsed, since `browsed`.
BROWSED = set()


async def _slow_browse(self, params):
    if self.external:
        BROWSED.update(
            d.NodeId.Identifier for d in params.NodesToBrowse if isinstance(d.NodeId.Identifier, str)
        )
    if BROWSE_DELAY[0]:
        await asyncio.sleep(BROWSE_DELAY[0])
    return await _browse(self, params)


InternalSession.browse = _slow_browse

# The sessions Writes came on, and those subscriptions were made on.
WRITE_SESSIONS = []
SUBSCRIPTION_SESSIONS = set()
_write = InternalSession.write
_create_subscription = InternalSession.create_subscription
_create_monitored_items = InternalSession.create_monitored_items
# Monitored items created (Good) by session, in the order sessions made any.
ITEMS = {}


async def _recorded_write(self, params):
    if not self.external:  # the server's own (`set`)
        return await _write(self, params)
    WRITE_SESSIONS.append(self.session_id)
    # As an S7-1500 does: a value written with a timestamp is refused
    # (BadWriteNotSupported); asyncua would take the client's.
    stamped = [bool(w.Value.SourceTimestamp or w.Value.ServerTimestamp) for w in params.NodesToWrite]
    params.NodesToWrite = [w for w, s in zip(params.NodesToWrite, stamped) if not s]
    written = iter(await _write(self, params) if params.NodesToWrite else [])
    refused = ua.StatusCode(ua.StatusCodes.BadWriteNotSupported)
    return [refused if s else next(written) for s in stamped]


async def _recorded_create_subscription(self, params, *args, **kwargs):
    SUBSCRIPTION_SESSIONS.add(self.session_id)
    return await _create_subscription(self, params, *args, **kwargs)


async def _recorded_create_monitored_items(self, params):
    results = await _create_monitored_items(self, params)
    if self.external:
        made = sum(1 for r in results if r.StatusCode.is_good())
        ITEMS[self.session_id] = ITEMS.get(self.session_id, 0) + made
    return results


InternalSession.write = _recorded_write
InternalSession.create_monitored_items = _recorded_create_monitored_items
InternalSession.create_subscription = _recorded_create_subscription


class Users(UserManager):
    def __init__(self, user, password):
        self.user, self.password = user, password

    def get_user(self, iserver, username=None, password=None, certificate=None):
        if username == self.user and password == self.password:
            return User(role=UserRole.User)
        return None


def option(name):
    return sys.argv[sys.argv.index(name) + 1] if name in sys.argv else None


async def certificates(base):
    from pathlib import Path
    from cryptography import x509
    from cryptography.x509.oid import ExtendedKeyUsageOID
    from asyncua.crypto.cert_gen import setup_self_signed_certificate

    base = Path(base)
    uses = [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
    (base / "server").mkdir(parents=True, exist_ok=True)
    server = (base / "server" / "key.pem", base / "server" / "cert.der")
    await setup_self_signed_certificate(
        server[0], server[1], SERVER_URI, "127.0.0.1", uses, {"commonName": "asyncua test PLC"}
    )
    for sub in ["own", "private"]:
        (base / "client-pki" / sub).mkdir(parents=True, exist_ok=True)
    await setup_self_signed_certificate(
        base / "client-pki" / "private" / "private.pem",
        base / "client-pki" / "own" / "cert.der",
        "urn:plccoms:client", "localhost", uses, {"commonName": "plccoms"},
    )
    return server


SERVER_URI = "urn:plccoms:test:plc"


async def main():
    port = int(sys.argv[1])
    user = option("--user")
    secure = option("--secure")
    if option("--max-sessions"):
        InternalSession.max_connections = int(option("--max-sessions"))
    server = Server(user_manager=Users(*user.split(":", 1)) if user else None)
    await server.init()
    server.set_endpoint(f"opc.tcp://127.0.0.1:{port}/plc")
    if secure:
        key, cert = await certificates(secure)
        await server.set_application_uri(SERVER_URI)
        await server.load_certificate(str(cert))
        await server.load_private_key(str(key))
        server.set_security_policy([ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt])
    else:
        server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
    if user:
        server.set_identity_tokens([ua.UserNameIdentityToken])
    ns = await server.register_namespace(NS_URI)
    objects = server.nodes.objects

    db = await objects.add_object(ua.NodeId("DB_LINE1", ns), ua.QualifiedName("DB_LINE1", ns))
    motor = await db.add_object(ua.NodeId("DB_LINE1.MOTOR", ns), ua.QualifiedName("MOTOR", ns))
    nodes = {}

    async def var(parent, prefix, name, value, vtype, writable=True, datatype=None):
        node = await parent.add_variable(
            ua.NodeId(f"{prefix}.{name}", ns),
            ua.QualifiedName(name, ns),
            ua.Variant(value, vtype),
            datatype=datatype,
        )
        if writable:
            await node.set_writable()
        nodes[name] = (node, vtype)
        return node

    await var(motor, "DB_LINE1.MOTOR", "SPEED", 1450.5, ua.VariantType.Double)
    await var(motor, "DB_LINE1.MOTOR", "RUNNING", True, ua.VariantType.Boolean)
    await var(motor, "DB_LINE1.MOTOR", "COUNT", 7, ua.VariantType.UInt32, writable=False)

    types = await objects.add_folder(ua.NodeId("TYPES", ns), ua.QualifiedName("TYPES", ns))
    stamp = datetime.datetime(2024, 3, 15, 13, 45, 30, 500000, tzinfo=datetime.timezone.utc)
    for name, value, vtype, datatype in [
        ("BOOL_V", False, ua.VariantType.Boolean, None),
        ("SBYTE_V", -5, ua.VariantType.SByte, None),
        ("BYTE_V", 200, ua.VariantType.Byte, None),
        ("INT16_V", -1234, ua.VariantType.Int16, None),
        ("UINT16_V", 54321, ua.VariantType.UInt16, None),
        ("INT32_V", -100000, ua.VariantType.Int32, None),
        ("UINT32_V", 4000000000, ua.VariantType.UInt32, None),
        ("INT64_V", -5000000000, ua.VariantType.Int64, None),
        ("UINT64_V", 12345678901234567890, ua.VariantType.UInt64, None),
        ("FLOAT_V", 1.5, ua.VariantType.Float, None),
        ("DOUBLE_V", -2.25, ua.VariantType.Double, None),
        ("STRING_V", "Hello", ua.VariantType.String, None),
        ("DATETIME_V", stamp, ua.VariantType.DateTime, None),
        ("DURATION_V", 1500.0, ua.VariantType.Double, ua.NodeId(290, 0)),
    ]:
        await var(types, "TYPES", name, value, vtype, datatype=datatype)
    arr = await objects.add_variable(
        ua.NodeId("ARRAY_V", ns), ua.QualifiedName("ARRAY_V", ns),
        ua.Variant([1, 2, 3], ua.VariantType.Int16),
    )
    await arr.write_value_rank(1)
    await arr.write_array_dimensions([3])
    await arr.set_writable()
    recipe_t, _ = await new_struct(
        server, ns, "RecipeT",
        [new_struct_field("TEMP", ua.VariantType.Double), new_struct_field("TIME", ua.VariantType.UInt32)],
    )
    await server.load_data_type_definitions()
    recipe = await objects.add_variable(
        ua.NodeId("RECIPE", ns), ua.QualifiedName("RECIPE", ns),
        ua.RecipeT(TEMP=21.5, TIME=30), datatype=recipe_t.nodeid,
    )
    nodes["RECIPE"] = (recipe, None)
    await var(recipe, "RECIPE", "TEMP", 21.5, ua.VariantType.Double)
    await var(recipe, "RECIPE", "TIME", 30, ua.VariantType.UInt32)
    empty = await objects.add_folder(ua.NodeId("EMPTY", ns), ua.QualifiedName("EMPTY", ns))
    await empty.add_folder(ua.NodeId("EMPTY.SUB", ns), ua.QualifiedName("SUB", ns))

    async with server:
        print("ready", flush=True)
        loop = asyncio.get_running_loop()
        while True:
            line = await loop.run_in_executor(None, sys.stdin.readline)
            if not line:
                # The test is gone (stdin closed): so is the server.
                break
            words = line.split()
            if words[:1] == ["add"]:
                await var(motor, "DB_LINE1.MOTOR", words[1], 1.5, ua.VariantType.Double)
            elif words[:1] == ["addto"]:
                parent, _ = nodes[words[1]]
                await var(parent, parent.nodeid.Identifier, words[2], 1.5, ua.VariantType.Double)
            elif words[:1] == ["browsed"]:
                print(" ".join(["browsed"] + sorted(BROWSED)), flush=True)
                BROWSED.clear()
            elif words[:1] == ["remove"]:
                node, _ = nodes.pop(words[1])
                await server.delete_nodes([node])
            elif words[:1] == ["slow"]:
                READ_DELAY[0] = int(words[1]) / 1000
            elif words[:1] == ["slowbrowse"]:
                BROWSE_DELAY[0] = int(words[1]) / 1000
            elif words[:1] == ["stamp"]:
                node, vtype = nodes[words[1]]
                at = datetime.datetime.fromtimestamp(int(words[3]) / 1000, datetime.timezone.utc)
                value = type(await node.read_value())(words[2])
                await node.write_value(ua.DataValue(ua.Variant(value, vtype), SourceTimestamp=at))
            elif words[:1] == ["status"]:
                # status NAME uncertain|good [VALUE]: the value (the same
                # unless given) with that StatusCode, stamped now.
                node, vtype = nodes[words[1]]
                value = (await node.read_data_value(raise_on_bad_status=False)).Value.Value
                if len(words) > 3:
                    value = type(value)(words[3])
                code = ua.StatusCodes.UncertainLastUsableValue if words[2] == "uncertain" else ua.StatusCodes.Good
                await node.write_value(ua.DataValue(
                    ua.Variant(value, vtype), StatusCode=ua.StatusCode(code),
                    SourceTimestamp=datetime.datetime.now(datetime.timezone.utc),
                ))
            elif words[:1] == ["wrote"]:
                shared = [s in SUBSCRIPTION_SESSIONS for s in WRITE_SESSIONS]
                if not shared:
                    print("wrote nothing", flush=True)
                elif not any(shared):
                    print("wrote apart", flush=True)
                elif all(shared):
                    print("wrote together", flush=True)
                else:
                    print("wrote mixed", flush=True)
            elif words[:1] == ["items"]:
                print(" ".join(["items"] + [str(n) for n in ITEMS.values()]), flush=True)
            elif words[:1] == ["set"]:
                node, vtype = nodes[words[1]]
                await node.write_value(ua.Variant(type(await node.read_value())(words[2]) if vtype != ua.VariantType.Boolean else words[2] == "1", vtype))
            print("done", flush=True)


asyncio.run(main())
