#!/bin/sh
# Generates the Python classes of the bus contract (proto/cellgate/v1/*.proto) into ./gen,
# with the protoc that grpcio-tools bundles (no system protoc needed).
#
#   python -m venv .venv && . .venv/bin/activate && pip install -r requirements.txt
#   ./gen.sh
set -eu
here=$(cd "$(dirname "$0")" && pwd)
proto=$(cd "$here/../../proto" && pwd)
python=${PYTHON:-python3}
rm -rf "$here/gen"
mkdir -p "$here/gen"
"$python" -m grpc_tools.protoc -I "$proto" --python_out="$here/gen" "$proto"/cellgate/v1/*.proto
echo "generated $(ls "$here"/gen/cellgate/v1/*_pb2.py | wc -l) modules in $here/gen/cellgate/v1"
