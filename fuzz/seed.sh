#!/usr/bin/env bash
# Builds the seed corpora fuzz/corpus/<target>/ from the repository: request
# lines from the command tests, the ini files, the public files, and EPSNET
# datagrams laid out as the codec and service tests and the service table in
# plc/src/epsnet/service.rs describe them. Seeds are named seed-<sha1>, so
# running it again adds nothing twice and keeps what the fuzzer found.
#
# Usage: fuzz/seed.sh            (needs bash and python3)
set -euo pipefail
cd "$(dirname "$0")/.."

exec python3 - <<'PY'
import hashlib, os, re, struct

ROOT = "."
CORPUS = os.path.join("fuzz", "corpus")
counts = {}

def put(target, data):
    d = os.path.join(CORPUS, target)
    os.makedirs(d, exist_ok=True)
    name = "seed-" + hashlib.sha1(data).hexdigest()[:16]
    with open(os.path.join(d, name), "wb") as f:
        f.write(data)
    counts[target] = counts.get(target, 0) + 1

def read(path):
    with open(os.path.join(ROOT, path), "rb") as f:
        return f.read()

# --- request lines -------------------------------------------------------
ESC = re.compile(rb'\\(x[0-9a-fA-F]{2}|.)')
def unescape(s):
    def one(m):
        e = m.group(1)
        if e[:1] == b"x":
            return bytes([int(e[1:], 16)])
        return {b"n": b"\n", b"r": b"\r", b"t": b"\t", b"0": b"\0"}.get(e, e)
    return ESC.sub(one, s)

lines = set()
literal = re.compile(rb'b?"((?:[^"\\]|\\.)*)"')
for path in ["tests/commands.rs", "tests/files.rs", "tests/reload.rs",
             "protocol/src/request.rs", "protocol/src/decoder.rs",
             "protocol/tests/properties.rs"]:
    for m in literal.finditer(read(path)):
        text = unescape(m.group(1))
        for line in re.split(rb"\r\n|\n|\r\0", text):
            if re.match(rb"^[ \t]*[A-Za-z]+[ \t]*:", line) or line.startswith(b"%"):
                lines.add(line)
# The value and mask forms the manual and the tests use.
lines.update([
    b"SET:test_1,-32768", b"SET:v_lreal,1.5e-300", b"SET:v_real,3.4028235e38",
    b"SET:v_dt,1700000000.5", b"SET:v_date,19700", b"SET:v_tod,86399999",
    b"SET:test_string,\"a \\\"quoted\\\" \\\\ text\"", b"SET:%RW10,65535",
    b"SET:%R5.3,1", b"SET:%SL48,4294967295", b"SET:%RD8,-0.0", b"SET:%RF4,nan",
    b"EN:t* 0.5", b"EN:*_set[*].* 1e3", b"DI:*", b"GETMEM:%R100 16",
    b"SETCONF:num_of_decimals,3", b"WRITEFILE:a.txt[3]=abc",
    b"GETFILE:dir/x[0]=", b"   ", b"t_zones_set[0].topit_tc",
])
for line in sorted(lines):
    put("request_line", line)

# --- decoder input: [max_line, max_block / 3, chunk seed] + bytes ----------
stream = b"\r\n".join(sorted(lines)) + b"\r\n"
telnet = bytes([0xff, 0xfd, 0x03, 0xff, 0xfb, 0x18, 0xff, 0xfa, 0x18, 0x00]) + \
    b"XTERM" + bytes([0xff, 0xf0, 0xff, 0xf4, 0xff, 0xff])
blocks = b"WRITEFILE:test.txt[7]=a\r\n\0\xff\x04b\r\nwriteFile:x[0]=\n" \
    b"WRITEFILEINFO:t.txt[34]=44 0 41854524393844 41854674928753GET:x\n" \
    b"WRITEFILE:big[900]=" + b"z" * 40 + b"\nGET:y\r\0\x04"
for head in [bytes([255, 255, 7]), bytes([16, 2, 3]), bytes([0, 0, 1]), bytes([64, 10, 200])]:
    put("input_decoder", head + stream[:3000])
    put("input_decoder", head + telnet + b"GET:x\r\n" + blocks)
    put("input_decoder", head + b"a" * 600 + b"\nGET:x\n")

# --- ini -------------------------------------------------------------------
for path in ["tests/data/vendor/PLCComS.ini", "PLCComS.ini.example"]:
    data = read(path)
    put("ini", data)
    put("ini", data.replace(b"\n", b"\r\n"))
    put("ini", b"\xef\xbb\xbf" + data[: len(data) // 2])

# --- history times (plccoms history --from/--to) --------------------------
for t in [b"now", b"-30s", b"-15m", b"-1h", b"-7d", b"-2w", b"2026-05-01",
          b"2026-05-01T12:00:00Z", b"2026-05-01T12:00:00.123+02:00"]:
    put("history_time", t)

# --- history blocks: mode 1 = the packed form before zstd (block.rs), -----
# mode 2 = the same sealed with its checksum, mode 0 = the stored form
block = bytes([1, 0x64, 3, 2, 0, 2, 5, 1, 0, 0xC8, 0x01, 0, 1, 2, 3, 14,
               0x3F, 0xF8, 0, 0, 0, 0, 0, 0, 2]) + b"ab" + bytes([0, 2, 0, 1, 0, 9])
put("history_block", bytes([1]) + block)
put("history_block", bytes([1]) + block[:-3])
put("history_block", bytes([2]) + block)
put("history_block", bytes([0]) + b"\x28\xb5\x2f\xfd" + block)

# --- public files ----------------------------------------------------------
for path in ["conf/demo.pub", "conf/FIXED.pub", "tests/data/vendor/FIXED_Foxtrot.pub"]:
    put("pubfile", read(path))
common = read("tests/common/mod.rs")
m = re.search(rb'FIXED_PUB: &\[u8\] =\s*b"((?:[^"\\]|\\.)*)"', common)
if m:
    put("pubfile", unescape(re.sub(rb"\\\n\s*", b"", m.group(1))))
put("pubfile", b"; comment\r\n __PLC_RUN S B 2 .2 BOOL PUB_INOUT\r\n"
    b" x R B 2.7 BOOL\r\n y\tR\tF\t16\tLREAL\tPUB_IN ; trailing\r\n"
    b" s R B 100 STRING[255] PUB_OUT\r\n X R B 3 INT\r\n"
    b" z R B 524287 BYTE\r\n w R B 524287 WORD\r\n;* Crc=\"DEADBEEF\"\r\n")

# --- EPSNET ------------------------------------------------------------------
def frame(da, sa, fc, data):
    body = bytes([da, sa, fc]) + data
    fcs = sum(body) % 256
    if len(body) <= 255:
        return bytes([0x68, len(body), len(body), 0x68]) + body + bytes([fcs, 0x16])
    return bytes([0x68, 0, 0, 0x68]) + struct.pack(">H", len(body)) + body + bytes([fcs, 0x16])

def packet(mesi, frames):
    body = b"".join(frames)
    out = struct.pack(">HBBH", mesi, 0x02, 0, len(body)) + body
    return out + b"\0" * (len(out) % 2)

PLC, US, FC_REQ, FC_ANS = 0x00, 0x7D, 0x63, 0x08
info_req = struct.pack(">I", 0x20) + struct.pack("<QQ", 133500000000000000, 133500000000000001)
requests = [
    b"\x01", b"\x02", bytes([0x08, 24, 3, 15, 13, 45, 30, 5]),
    b"\x10R" + struct.pack(">IH", 100, 16), b"\x10S" + struct.pack(">IH", 0, 1230),
    b"\x10X" + struct.pack(">IH", 16383, 2),
    b"\x11R" + struct.pack(">I", 100) + b"\x01\x02\x03",
    b"\x12S" + struct.pack(">I", 2) + b"\x04\x00",
    b"\x20a.txt", b"\x20d/b.bin", b"\x20../etc",
    b"\x21" + struct.pack(">QH", 0, 1150) + b"a.txt",
    b"\x22" + struct.pack(">QBB", 0, 1, 5) + b"n.txt" + b"new data",
    b"\x22" + struct.pack(">QBB", 0, 0, 5) + b"m.txt" + b"part",
    b"\x23" + info_req + b"a.txt",
    b"\x24" + struct.pack(">H", 0) + b"/", b"\x24" + struct.pack(">H", 1) + b"d",
    b"\x77",
]
for i, r in enumerate(requests):
    put("epsnet_device", packet(i, [frame(PLC, US, FC_REQ, r)]))
put("epsnet_device", packet(9, [frame(PLC, US, FC_REQ, r) for r in requests[:6]]))
put("epsnet_device", packet(10, [frame(PLC, US, FC_REQ, requests[4])] * 2))
put("epsnet_device", b"NEXT".join([
    packet(1, [frame(PLC, US, FC_REQ, requests[13])]),
    packet(2, [frame(PLC, US, FC_REQ, b"\x22" + struct.pack(">QBB", 4, 1, 5) + b"m.txt" + b"rest")]),
    packet(3, [frame(PLC, US, FC_REQ, b"\x21" + struct.pack(">QH", 0, 100) + b"m.txt")]),
    packet(4, [frame(PLC, US, FC_REQ, requests[15])]),
]))
# The SETTID golden bytes of the codec tests, and a bare E5.
put("epsnet_device", packet(0x1234, [frame(0x00, 0x7D, 0x63, bytes([0x08, 24, 3, 15, 13, 45, 30, 5]))]))
put("epsnet_device", packet(1, [b"\xe5"]))

fileinfo = struct.pack(">QI", 22, 0x20) + struct.pack("<QQ", 133500000000000000, 133500000000000001)
answers = [
    (0, frame(US, PLC, FC_ANS, b"\x01\x00CP1000    SIM 1.0 1.0")),
    (0, frame(US, PLC, FC_ANS, b"\x02\x00\x00\x01")),
    (16, frame(US, PLC, FC_ANS, b"\x10\x00" + bytes(range(16)))),
    (1230, frame(US, PLC, FC_ANS, b"\x10\x00" + bytes(1230))),
    (0, frame(US, PLC, FC_ANS, b"\x10\x0c")),
    (100, frame(US, PLC, FC_ANS, b"\x21\x00This is test string 1.")),
    (0, frame(US, PLC, FC_ANS, b"\x20\x00" + fileinfo)),
    (0, frame(US, PLC, FC_ANS, b"\x24\x00\x01" + fileinfo + b"\x05a.txt" + fileinfo + b"\x01d")),
    (0, b"\xe5"),
]
for length, f in answers:
    put("epsnet_client", struct.pack(">H", length) + packet(7, [f]))
put("epsnet_client", struct.pack(">H", 16) + packet(8, [f for _, f in answers[:3]] + [b"\xe5"]))

# A serial line: chunk size, then frames back to back, with noise and a
# truncated frame.
line = b"".join(f for _, f in answers)
put("epsnet_stream", b"\x01" + line)
put("epsnet_stream", b"\x07" + b"\x00\x16\x68" + line[:40] + line)
put("epsnet_stream", b"\xff" + frame(PLC, US, FC_REQ, requests[12]) + b"\xe5\x68\x00\x00\x68\xff\xff")

for query in [b"section=Demo&vars=SIN*,counter&from=0&to=1000&format=csv",
              b"section=D%20x&vars=%E8&from=2026-11-30T12:00:00Z&format=json",
              b"section=Demo&from=-5&to=-9", b"vars=a&section=&to=1e9"]:
    put("web_query", query)

# --- MQTT --------------------------------------------------------------------
# Queue records as src/mqtt/spool.rs writes them (crc32c = CRC-32/ISCSI).
def crc32c(data):
    crc = 0xFFFFFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF

def record(seq, topic, payload, qos=1, retain=True):
    body = struct.pack("<QBH", seq, qos | (4 if retain else 0), len(topic)) + topic + payload
    return struct.pack("<II", len(body), crc32c(body)) + body

put("mqtt_spool", record(1, b"plccoms/Demo/COUNTER", b"42"))
put("mqtt_spool", record(7, b"plccoms/Demo/A%2FB", b'{"value":1}', 0, False) + record(8, b"t", b""))
for text in [b"mqtt://broker.lan:1883", b"mqtts://[::1]:8883/", b"tcp://10.0.0.1",
             b"COUNTER", b"A%2FB%2BC%23D%25E", "TEPLOTA_KUCHYNĚ".encode(), b"%zz"]:
    put("mqtt_text", text)
for text in [b"2026-11-25T10:15:00.123Z", b"2026-11-25T11:15:00+01:00", b"2026-11-25",
             b"10:15:00.123", b"07:30", b"PT1H2M3.456S", b"P1DT0.25S", b"PT0S", b"5.0", b"-1e3"]:
    put("user_value", text)
# --- Modbus ------------------------------------------------------------------
put("modbus_tags", read("conf/demo-modbus.csv"))
put("modbus_tags", "name,type,table,address,bit,order,scale,offset,access,unit,description\n"
    "a,INT,holding,0\nb,REAL,input,65534,,CDAB\nc,BOOL,holding,3,15\nd,TS48,holding,9\n"
    "e,STRING[7],holding,20,,BADC\nf,UINT,input,1,,,0.1,-40,ro,°C,\"x, y\"\n"
    "g,BOOL,coil,65535\nh,LREAL,holding,65533\n# comment\n\nbad,INT,holdng,1\n".encode())
put("modbus_tags", b"Name;Type\nx;INT\n")

def adu(tid, pdu, unit=1):
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu
answers = [
    (8, adu(1, b"\x01\x01\xa5")),
    (8, adu(2, b"\x02\x01\x0f")),
    (2, adu(3, b"\x03\x04\xbe\xef\x00\x01")),
    (2, adu(4, b"\x04\x04\x12\x34\x56\x78")),
    (0, adu(5, b"\x05\x00\x04\xff\x00")),
    (2, adu(6, b"\x10\x00\x07\x00\x02")),
    (0, adu(7, b"\x16\x00\x08\x00\x00\xff\xff")),
    (0, adu(8, b"\x83\x02")),
    (0, adu(9, b"\x84\x0b")),
]
for count, a in answers:
    put("modbus_answer", struct.pack(">H", count) + a)
put("modbus_answer", struct.pack(">H", 2) + b"".join(a for _, a in answers) + b"\x00\x01\x00")

for target in sorted(counts):
    print(f"{target}: {counts[target]} seeds")
PY
