"""pyads's ADS test server, its advanced handler extended where it falls
short of a TwinCAT PLC (each gap marked GAP), as the ADS tests' device;
pyads's own client works against it (tests/ads/pyads_client.py).

Started by tests/ads_*.rs: prints `port <n>` once listening (an ephemeral
loopback port unless one is given), then takes one command a line on stdin
and answers each with one line:

  set <name> <hex>        write a value as the PLC program would (notifies)
  stamp <filetime>        the PLC clock for the next notifications (0: now)
  forget <name>           the symbol gone, the version kept (a refusal)
  remove <name>           a new program without that symbol (version + 1)
  add <name> <type> <hex> a new program with that symbol (version + 1)
  state RUN|STOP          the ADS state ReadState answers
  silent 1|0              drop every request (a cable pulled), or answer again
  count                   `handles <n> notifications <m>` held for clients
  get <name>              the value's hex
  quit
"""
import ctypes
import select
import socket
import struct
import sys
import threading
import time

from pyads import constants
from pyads.testserver import AdsTestServer, AdvancedHandler, PLCVariable
from pyads.testserver.handler import AmsResponseData
from pyads.testserver.testserver import AdsClientConnection

SYM_VERSION = 0xF008
SYM_DT_UPLOAD = 0xF00E
SUMUP_READWRITE = 0xF082
ADSCOMMAND_DEVICENOTE = 8
ADSSTATE_STOP = 6
SYMBOL_NOT_FOUND = 0x710
NOTIFICATION_HANDLE_INVALID = 0x714

# Type name -> (ADS type id, size)
TYPES = {
    "BOOL": (33, 1), "BYTE": (17, 1), "WORD": (18, 2), "DWORD": (19, 4),
    "LWORD": (21, 8), "SINT": (16, 1), "USINT": (17, 1), "INT": (2, 2),
    "UINT": (18, 2), "DINT": (3, 4), "UDINT": (19, 4), "LINT": (20, 8),
    "ULINT": (21, 8), "REAL": (4, 4), "LREAL": (5, 8), "STRING(80)": (30, 81),
    "TIME": (19, 4), "TOD": (19, 4), "DATE": (19, 4), "DT": (19, 4),
}

# Data types the symbol table refers to: name -> (size, [(field, type, offset, size, dims)])
STRUCTS = {
    "ST_Pair": (7, [("on", "BOOL", 0, 1, []), ("n", "ARRAY [0..2] OF WORD", 1, 6, [(0, 3)])]),
}


def filetime_now():
    return int(time.time() * 1e7) + 116444736000000000


class View(PLCVariable):
    """A field or element of a symbol, sharing its bytes: a handle by name
    (`MAIN.st.n[1]`, `MAIN.arr[2]`) reads and writes the symbol's memory."""

    def __init__(self, name, parent, offset, size):
        self.parent, self.at, self._size, self.ready = parent, offset, size, False
        super().__init__(name, bytes(size), constants.ADST_UINT8, "BYTE")
        self.ready = True

    @property
    def value(self):
        return self.parent.value[self.at:self.at + self._size]

    @value.setter
    def value(self, data):
        if self.ready:
            whole = bytearray(self.parent.value)
            whole[self.at:self.at + self._size] = data[:self._size]
            self.parent.write(bytes(whole))


class Handler(AdvancedHandler):
    def __init__(self):
        super().__init__()
        self.version = 1
        self.ads_state = constants.ADSSTATE_RUN
        self.views = {}
        self.stamp = 0
        self.lock = threading.RLock()
        self.connection = None
        # notification handle -> (connection, var, target/source addresses)
        self.notes = {}
        self.next_note = 100
        self.silent = False

    # -- the program's symbols --------------------------------------------

    def add(self, name, type_name, value):
        if type_name in TYPES:
            ads_type, size = TYPES[type_name]
        elif type_name.startswith("ARRAY"):
            ads_type, size = 65, len(value)
        else:
            ads_type, size = 65, STRUCTS[type_name][0]
        var = PLCVariable(name, bytes(value).ljust(size, b"\0")[:size], ads_type, type_name,
                          index_group=0x4040, index_offset=0x1000 * (len(self._data) + 1))
        self.add_variable(var)
        for sub, offset, size in self.parts(name, type_name, size):
            self.views[sub.lower()] = View(sub, var, offset, size)

    def parts(self, name, type_name, size):
        if type_name in STRUCTS:
            for field, ftype, offset, fsize, _ in STRUCTS[type_name][1]:
                yield f"{name}.{field}", offset, fsize
                for sub, o, s in self.parts(f"{name}.{field}", ftype, fsize):
                    yield sub, offset + o, s
        elif type_name.startswith("ARRAY"):
            low, high = type_name[type_name.index("[") + 1:type_name.index("]")].split("..")
            count = int(high) - int(low) + 1
            for i in range(count):
                yield f"{name}[{int(low) + i}]", i * (size // count), size // count

    def store(self, var, value):
        """A new value of a symbol or of part of one, notified."""
        if isinstance(var, View):
            var.value = value
            var = var.parent
        else:
            var.write(value)
        self.notify(var)

    def remove(self, name):
        for key, var in list(self._data.items()):
            if var.name.lower() == name.lower():
                del self._data[key]
        for key in [k for k in self.views if k.startswith(name.lower() + ".") or k.startswith(name.lower() + "[")]:
            del self.views[key]

    def find(self, name):
        name = name.strip("\x00").lower()
        for var in self._data.values():
            if var.name.lower() == name:
                return var
        return self.views.get(name)

    def by_handle(self, handle):
        for var in list(self._data.values()) + list(self.views.values()):
            if var.handle == handle and getattr(var, "held", False):
                return var
        return None

    # -- GAP: notifications reach the client over its own connection ------
    # (pyads calls callbacks of its own process only)

    def notify(self, var):
        stamp = self.stamp or filetime_now()
        for handle, (conn, watched, addrs) in list(self.notes.items()):
            if watched is var or (isinstance(watched, View) and watched.parent is var):
                data = watched.value
                body = struct.pack("<IQI", 1, stamp, 1) + struct.pack("<II", handle, len(data)) + data
                body = struct.pack("<I", len(body)) + body
                conn.send_packet(addrs, ADSCOMMAND_DEVICENOTE, 0x0004, body)

    def handle_request(self, request):
        with self.lock:
            return self._handle(request)

    def _handle(self, request):
        h = request.ams_header
        command = struct.unpack("<H", h.command_id)[0]
        state = struct.pack("<H", struct.unpack("<H", h.state_flags)[0] | 1)
        data = h.data

        def answer(result, content=b""):
            return AmsResponseData(state, b"\0\0\0\0", struct.pack("<I", result) + content)

        def read_answer(payload):
            return answer(0, struct.pack("<I", len(payload)) + payload)

        if command == constants.ADSCOMMAND_READSTATE:
            return answer(0, struct.pack("<HH", self.ads_state, 0))
        if command == constants.ADSCOMMAND_READ:
            group, offset, length = struct.unpack("<III", data[:12])
            # GAP: the symbol version (pyads drops the connection).
            if group == SYM_VERSION:
                return read_answer(bytes([self.version & 0xFF]))
            # GAP: upload info with the real lengths, and named entries.
            if group == constants.ADSIGRP_SYM_UPLOADINFO2:
                table, types = self.symbol_table(), self.type_table()
                return read_answer(struct.pack("<IIIIII", len(self._data), len(table),
                                               len(STRUCTS), len(types), 0, 0))
            if group == constants.ADSIGRP_SYM_UPLOAD:
                return read_answer(self.symbol_table())
            # GAP: data types (pyads has none).
            if group == SYM_DT_UPLOAD:
                return read_answer(self.type_table())
            if group == constants.ADSIGRP_SYM_VALBYHND:
                var = self.by_handle(offset)
                if var is None:
                    return answer(SYMBOL_NOT_FOUND, struct.pack("<I", 0))
                return read_answer(var.value[:length])
        if command == constants.ADSCOMMAND_WRITE:
            group, offset, length = struct.unpack("<III", data[:12])
            value = data[12:12 + length]
            if group == constants.ADSIGRP_SYM_RELEASEHND:
                var = self.by_handle(struct.unpack("<I", value[:4])[0])
                if var is not None:
                    var.held = False
                return answer(0)
            if group == constants.ADSIGRP_SYM_VALBYHND:
                var = self.by_handle(offset)
                if var is None:
                    return answer(SYMBOL_NOT_FOUND)
                if len(value) != var.size:
                    return answer(0x705)
                self.store(var, bytes(value))
                return answer(0)
        if command == constants.ADSCOMMAND_READWRITE:
            group, offset, read_len, write_len = struct.unpack("<IIII", data[:16])
            payload = data[16:16 + write_len]
            # GAP: an unknown name answers 0x710 (pyads drops the connection).
            if group in (constants.ADSIGRP_SYM_HNDBYNAME, constants.ADSIGRP_SYM_INFOBYNAMEEX):
                var = self.find(payload.decode("latin-1"))
                if var is None:
                    return answer(SYMBOL_NOT_FOUND, struct.pack("<I", 0))
                if group == constants.ADSIGRP_SYM_HNDBYNAME:
                    var.held = True
                    return read_answer(struct.pack("<I", var.handle))
            # GAP: sum reads by handle (pyads takes index group/offset only).
            if group == constants.ADSIGRP_SUMUP_READ:
                codes, values = b"", b""
                for i in range(offset):
                    g, o, size = struct.unpack_from("<III", payload, 12 * i)
                    var = self.by_handle(o) if g == constants.ADSIGRP_SYM_VALBYHND else self._data.get((g, o))
                    codes += struct.pack("<I", 0 if var else SYMBOL_NOT_FOUND)
                    values += (var.value[:size] if var else b"").ljust(size, b"\0")
                return read_answer(codes + values)
            # GAP: sum read-write, here for handles by name.
            if group == SUMUP_READWRITE:
                heads, tail, at = b"", b"", 16 * offset
                for i in range(offset):
                    g, o, rlen, wlen = struct.unpack_from("<IIII", payload, 16 * i)
                    name = payload[at:at + wlen].decode("latin-1")
                    at += wlen
                    var = self.find(name) if g == constants.ADSIGRP_SYM_HNDBYNAME else None
                    if var is None:
                        heads += struct.pack("<II", SYMBOL_NOT_FOUND, 0)
                    else:
                        var.held = True
                        heads += struct.pack("<II", 0, 4)
                        tail += struct.pack("<I", var.handle)
                return read_answer(heads + tail)
        if command == constants.ADSCOMMAND_ADDDEVICENOTE:
            group, offset, length = struct.unpack("<III", data[:12])
            var = self.by_handle(offset) if group == constants.ADSIGRP_SYM_VALBYHND else self._data.get((group, offset))
            if var is None:
                return answer(SYMBOL_NOT_FOUND, struct.pack("<I", 0))
            handle = self.next_note
            self.next_note += 1
            self.notes[handle] = (self.connection, var, h)
            # TwinCAT sends the value at once, then its changes.
            threading.Timer(0.01, self.notify_one, (handle,)).start()
            return answer(0, struct.pack("<I", handle))
        if command == constants.ADSCOMMAND_DELDEVICENOTE:
            handle = struct.unpack("<I", data[:4])[0]
            if self.notes.pop(handle, None) is None:
                return answer(NOTIFICATION_HANDLE_INVALID)
            return answer(0)
        try:
            return super().handle_request(request)
        except KeyError:
            # GAP: a refusal rather than a dropped connection.
            return answer(SYMBOL_NOT_FOUND, struct.pack("<I", 0))

    def notify_one(self, handle):
        with self.lock:
            note = self.notes.get(handle)
            if note:
                conn, var, addrs = note
                stamp = self.stamp or filetime_now()
                data = var.value
                body = struct.pack("<IQI", 1, stamp, 1) + struct.pack("<II", handle, len(data)) + data
                conn.send_packet(addrs, ADSCOMMAND_DEVICENOTE, 0x0004, struct.pack("<I", len(body)) + body)

    def symbol_table(self):
        return b"".join(var.get_packed_info() for var in self._data.values())

    def type_table(self):
        out = b""
        for name, (size, fields) in STRUCTS.items():
            subs = b"".join(self.type_entry(f, t, o, s, d, []) for f, t, o, s, d in fields)
            out += self.type_entry(name, "", 0, size, [], [subs] if subs else [], len(fields))
        return out

    @staticmethod
    def type_entry(name, type_name, offset, size, dims, subs, count=0):
        n, t = name.encode(), type_name.encode()
        body = struct.pack("<IIIIIIIHHHHH", 1, 0, 0, size, offset, 65, 0, len(n), len(t), 0, len(dims), count)
        body += n + b"\0" + t + b"\0" + b"\0"
        for low, elements in dims:
            body += struct.pack("<iI", low, elements)
        body += b"".join(subs)
        return struct.pack("<I", len(body) + 4) + body


class Connection(AdsClientConnection):
    # GAP: a request split over several recv calls, or several in one, are
    # framed by their AMS/TCP length (pyads takes one recv as one request).
    def run(self):
        buffer = b""
        self.send_lock = threading.Lock()
        while self._run:
            ready, _, _ = select.select([self.client], [], [], 0.1)
            if not ready:
                continue
            try:
                chunk = self.client.recv(65536)
            except OSError:
                chunk = b""
            if not chunk:
                self.client.close()
                self._run = False
                self.server.handler.drop(self)
                continue
            buffer += chunk
            while len(buffer) >= 6:
                length = struct.unpack_from("<I", buffer, 2)[0]
                if len(buffer) < 6 + length:
                    break
                frame, buffer = buffer[:6 + length], buffer[6 + length:]
                request = self.construct_request(frame)
                handler = self.server.handler
                if handler.silent:
                    continue
                with handler.lock:
                    handler.connection = self
                    response = handler.handle_request(request)
                with self.send_lock:
                    self.client.send(self.construct_response(response, request))

    def send_packet(self, request_header, command, state, data):
        h = request_header
        header = (h.source_net_id + h.source_port + h.target_net_id + h.target_port
                  + struct.pack("<HHIII", command, state, len(data), 0, 0))
        packet = struct.pack("<HI", 0, len(header) + len(data)) + header + data
        try:
            with self.send_lock:
                self.client.send(packet)
        except OSError:
            pass


def _drop(self, conn):
    """Notifications of a closed connection are gone, as on TwinCAT."""
    with self.lock:
        for handle in [k for k, v in self.notes.items() if v[0] is conn]:
            del self.notes[handle]


Handler.drop = _drop


class Server(AdsTestServer):
    def run(self):
        self._run = True
        self.server.listen(5)
        while self._run:
            ready, _, _ = select.select([self.server], [], [], 0.1)
            if ready:
                try:
                    client, address = self.server.accept()
                except OSError:
                    continue
                conn = Connection(handler=self.handler, client=client, address=address, server=self)
                conn.daemon = True
                conn.start()
                self.clients.append(conn)


def demo_program(handler):
    values = {
        "BOOL": b"\x01", "BYTE": b"\x12", "WORD": struct.pack("<H", 0xBEEF),
        "DWORD": struct.pack("<I", 0xDEADBEEF), "LWORD": struct.pack("<Q", 2**40),
        "SINT": struct.pack("<b", -5), "USINT": b"\xfa", "INT": struct.pack("<h", -1234),
        "UINT": struct.pack("<H", 54321), "DINT": struct.pack("<i", -123456),
        "UDINT": struct.pack("<I", 4000000000), "LINT": struct.pack("<q", -2**40),
        "ULINT": struct.pack("<Q", 2**63), "REAL": struct.pack("<f", 1.5),
        "LREAL": struct.pack("<d", -2.25), "STRING(80)": b"Hello ADS",
        "TIME": struct.pack("<I", 1500), "TOD": struct.pack("<I", 3723000),
        "DATE": struct.pack("<I", 1710460800), "DT": struct.pack("<I", 1710510330),
    }
    for type_name, value in values.items():
        name = "MAIN.v" + type_name.split("(")[0].lower()
        handler.add(name, type_name, value)
    handler.add("MAIN.st", "ST_Pair", b"\x01" + struct.pack("<HHH", 10, 20, 30))
    handler.add("MAIN.arr", "ARRAY [1..3] OF DINT", struct.pack("<iii", 7, -8, 9))
    handler.add("MAIN.counter", "DINT", struct.pack("<i", 0))
    # The program's clock, written every cycle (10 ms): ms of the day, UTC.
    handler.add("MAIN.tim", "UDINT", struct.pack("<I", 0))
    tim = handler.find("MAIN.tim")

    def cycle():
        while True:
            with handler.lock:
                tim.write(struct.pack("<I", int(time.time() * 1000) % 86400000))
            time.sleep(0.01)

    threading.Thread(target=cycle, daemon=True).start()


def main():
    port = int(sys.argv[1]) if len(sys.argv) > 1 else 0
    handler = Handler()
    demo_program(handler)
    server = Server(handler=handler, ip_address="127.0.0.1", port=port, logging=False)
    server.start()
    print("port", server.server.getsockname()[1], flush=True)
    for line in sys.stdin:
        words = line.split()
        if not words:
            continue
        reply = "ok"
        with handler.lock:
            if words[0] == "set":
                handler.store(handler.find(words[1]), bytes.fromhex(words[2]))
            elif words[0] == "stamp":
                handler.stamp = int(words[1])
            elif words[0] == "forget":
                handler.remove(words[1])
            elif words[0] == "remove":
                handler.remove(words[1])
                handler.version += 1
            elif words[0] == "add":
                handler.add(words[1], words[2], bytes.fromhex(words[3]))
                handler.version += 1
            elif words[0] == "silent":
                handler.silent = words[1] == "1"
            elif words[0] == "state":
                handler.ads_state = constants.ADSSTATE_RUN if words[1] == "RUN" else ADSSTATE_STOP
            elif words[0] == "count":
                held = sum(1 for v in list(handler._data.values()) + list(handler.views.values())
                           if getattr(v, "held", False))
                reply = f"handles {held} notifications {len(handler.notes)}"
            elif words[0] == "get":
                reply = handler.find(words[1]).value.hex()
            elif words[0] == "quit":
                break
        print(reply, flush=True)
    server.stop()


if __name__ == "__main__":
    main()
