"""pyads's own client against our fixture (tests/ads/fixture.py on
127.0.0.1:48898, the port pyads's router always uses): the fixture must be
an ADS device pyads itself accepts. Exits non-zero on the first failure."""
import time

import pyads

pyads.open_port()
pyads.set_local_address("127.0.0.1.1.1")
plc = pyads.Connection("127.0.0.1.1.1", 851, "127.0.0.1")
plc.open()
assert plc.read_state()[0] == pyads.ADSSTATE_RUN
assert plc.read_by_name("MAIN.vint", pyads.PLCTYPE_INT) == -1234
plc.write_by_name("MAIN.vint", 99, pyads.PLCTYPE_INT)
assert plc.read_by_name("MAIN.vint", pyads.PLCTYPE_INT) == 99
assert plc.read_by_name("MAIN.st.n[1]", pyads.PLCTYPE_WORD) == 20
names = [s.name for s in plc.get_all_symbols()]
assert "MAIN.vbool" in names and "MAIN.st" in names, names
assert plc.read_list_by_name(["MAIN.vint", "MAIN.vdint"]) == {"MAIN.vint": 99, "MAIN.vdint": -123456}
got = []


def changed(notification, data):
    got.append(plc.parse_notification(notification, pyads.PLCTYPE_DINT)[2])


handles = plc.add_device_notification("MAIN.counter", pyads.NotificationAttrib(4), changed)
time.sleep(0.3)
plc.write_by_name("MAIN.counter", 5, pyads.PLCTYPE_DINT)
deadline = time.time() + 5
while got[-1:] != [5] and time.time() < deadline:
    time.sleep(0.05)
assert got[-1:] == [5], got
plc.del_device_notification(*handles)
try:
    plc.read_by_name("MAIN.nothere", pyads.PLCTYPE_INT)
    raise AssertionError("an unknown name was read")
except pyads.ADSError as e:
    assert e.err_code == 0x710, e.err_code
plc.close()
print("pyads client: ok")
