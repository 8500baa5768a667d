"""Fetches /metrics and parses it with prometheus_client's text parser (the
reference parser of the Prometheus text format); prints what it parsed as
JSON for tests/web.rs: {family: {"type": t, "samples": [[name, labels, value]]}}.
Any parse error fails (exit 1) with the parser's message.

    python3 check_metrics.py <url> [bearer token]
"""
import json
import sys
import urllib.request

from prometheus_client.parser import text_string_to_metric_families


def main():
    url = sys.argv[1]
    request = urllib.request.Request(url)
    if len(sys.argv) > 2:
        request.add_header("Authorization", "Bearer " + sys.argv[2])
    with urllib.request.urlopen(request, timeout=10) as response:
        content_type = response.headers.get("Content-Type", "")
        text = response.read().decode("utf-8")
    families = {}
    for family in text_string_to_metric_families(text):
        if family.name in families:
            raise SystemExit("family %s appears twice" % family.name)
        families[family.name] = {
            "type": family.type,
            "help": family.documentation,
            "samples": [[s.name, s.labels, s.value] for s in family.samples],
        }
    print(json.dumps({"content_type": content_type, "families": families}))


if __name__ == "__main__":
    main()
