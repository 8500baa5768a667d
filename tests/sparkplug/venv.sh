#!/bin/sh
# Makes the venv of tests/sparkplug.rs when it is missing: pysparkplug
# needs paho-mqtt < 2, which other tests' packages may not want beside it.
# Prints the venv's python.
set -e
venv="${1:-target/sparkplug-venv}"
if ! "$venv/bin/python" -c 'import pysparkplug, paho.mqtt' 2>/dev/null; then
    python3 -m venv "$venv" >&2
    "$venv/bin/pip" install --quiet 'pysparkplug==0.6.1' 'paho-mqtt<2' >&2
fi
echo "$venv/bin/python"
