"""A Sparkplug B host's ears and mouth for tests/sparkplug.rs: pysparkplug
(a third-party decoder) decodes and encodes every payload, paho-mqtt moves
them.

  spb.py listen PORT       every message under spBv1.0/#, one JSON line each
  spb.py cmd PORT TOPIC JSON  an NCMD/DCMD: JSON is a list of
                           {"name"|"alias", "datatype", "value"}
  spb.py state PORT HOST ONLINE TIMESTAMP   a retained STATE (spec 3.0 JSON)
"""

import datetime
import json
import sys

import paho.mqtt.client as mqtt
import pysparkplug as spb
from pysparkplug._protobuf import sparkplug_b_pb2 as pb

KINDS = {
    "NBIRTH": spb.NBirth,
    "DBIRTH": spb.DBirth,
    "NDATA": spb.NData,
    "DDATA": spb.DData,
    "NCMD": spb.NCmd,
    "DCMD": spb.DCmd,
    "NDEATH": spb.NDeath,
    "DDEATH": spb.DDeath,
}


def plain(value):
    if isinstance(value, datetime.datetime):
        return int(value.timestamp() * 1000)
    if isinstance(value, float) and value != value:
        return "nan"
    return value


def properties(raw_metric):
    out = {}
    for key, value in zip(raw_metric.properties.keys, raw_metric.properties.values):
        field = value.WhichOneof("value")
        out[key] = getattr(value, field) if field else None
    return out


def listen(port):
    births = {}

    def on_connect(client, userdata, flags, rc):
        client.subscribe("spBv1.0/#", qos=1)
        print(json.dumps({"type": "ready"}), flush=True)

    def on_message(client, userdata, msg):
        levels = msg.topic.split("/")
        if levels[1] == "STATE":
            return
        kind = levels[2]
        key = tuple(levels[3:])
        line = {"topic": msg.topic, "type": kind, "device": levels[4] if len(levels) > 4 else None}
        try:
            cls = KINDS[kind]
            birth = births.get(key) if kind in ("DDATA", "NDATA", "DCMD", "NCMD") else None
            decoded = cls.decode(msg.payload, birth=birth) if birth else cls.decode(msg.payload)
            if kind in ("NBIRTH", "DBIRTH"):
                births[key] = decoded
            raw = pb.Payload.FromString(msg.payload)
            line["seq"] = raw.seq if raw.HasField("seq") else None
            line["timestamp"] = raw.timestamp if raw.HasField("timestamp") else None
            metrics = []
            if kind == "NDEATH":
                found = [decoded.bd_seq_metric]
            else:
                found = list(getattr(decoded, "metrics", ()))
            for metric, raw_metric in zip(found, raw.metrics):
                metrics.append({
                    "name": metric.name,
                    "alias": metric.alias,
                    "datatype": int(metric.datatype),
                    "value": plain(metric.value),
                    "timestamp": metric.timestamp,
                    "is_historical": metric.is_historical,
                    "is_null": metric.is_null,
                    "properties": properties(raw_metric),
                })
            line["metrics"] = metrics
        except Exception as e:  # a payload pysparkplug cannot read is a finding
            line["error"] = repr(e)
        print(json.dumps(line), flush=True)

    client = mqtt.Client(client_id="spb-listener", clean_session=True)
    client.on_connect = on_connect
    client.on_message = on_message
    client.connect("127.0.0.1", port)
    client.loop_forever()


def publish(port, topic, payload, retain=False):
    client = mqtt.Client(client_id="", clean_session=True)
    client.connect("127.0.0.1", port)
    client.loop_start()
    client.publish(topic, payload, qos=1, retain=retain).wait_for_publish()
    client.loop_stop()
    client.disconnect()


def cmd(port, topic, metrics_json):
    kind = topic.split("/")[2]
    metrics = tuple(
        spb.Metric(
            timestamp=spb.get_current_timestamp(),
            name=m.get("name"),
            alias=m.get("alias"),
            datatype=spb.DataType(m["datatype"]),
            value=m.get("value"),
        )
        for m in json.loads(metrics_json)
    )
    payload = KINDS[kind](timestamp=spb.get_current_timestamp(), metrics=metrics)
    publish(port, topic, payload.encode(include_dtypes=True))


def state(port, host, online, timestamp):
    payload = spb.State(timestamp=int(timestamp), online=online == "true").encode()
    publish(port, f"spBv1.0/STATE/{host}", payload, retain=True)


if __name__ == "__main__":
    what, port = sys.argv[1], int(sys.argv[2])
    if what == "listen":
        listen(port)
    elif what == "cmd":
        cmd(port, sys.argv[3], sys.argv[4])
    elif what == "state":
        state(port, sys.argv[3], sys.argv[4], sys.argv[5])
