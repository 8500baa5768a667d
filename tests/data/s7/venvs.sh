#!/usr/bin/env bash
# The two S7 servers the tests start, each in a venv of its own under
# target/s7-venvs (created when missing; .ci/run calls this too):
#   py3: python-snap7 3.3.0, the pure-Python server
#   c1:  python-snap7 1.4.1, whose wheel ships the Snap7 C library
set -euo pipefail
root=${1:-"$(cd "$(dirname "${BASH_SOURCE[0]}")/../../.." && pwd)/target/s7-venvs"}
make() {
    local name=$1 spec=$2
    local py="$root/$name/bin/python"
    if [ -x "$py" ] && "$py" -c "import snap7.server" 2>/dev/null; then
        return
    fi
    python3 -m venv "$root/$name"
    for attempt in 1 2 3; do
        if "$root/$name/bin/pip" install -q --disable-pip-version-check "$spec" </dev/null; then
            return
        fi
        [ "$attempt" -eq 3 ] && { echo "pip install $spec failed" >&2; exit 1; }
        sleep 10
    done
}
make py3 'python-snap7==3.3.0'
make c1 'python-snap7==1.4.1'
