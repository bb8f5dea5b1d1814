#!/usr/bin/env bash
# Checks the Kubernetes manifests: every resource against the Kubernetes 1.31 schemas
# (kubernetes-validate, strict: unknown fields are errors), and every cell file a ConfigMap
# carries with `cellgate check-config`.
#
#   deploy/k8s/check.sh [CELLGATE_BINARY]
set -euo pipefail
cd "$(dirname "$0")"
cellgate="${1:-${CARGO_TARGET_DIR:-../../target}/debug/cellgate}"

venv="${CELLGATE_K8S_VENV:-${TMPDIR:-/tmp}/cellgate-k8s-venv}"
if [ ! -x "$venv/bin/kubernetes-validate" ]; then
    python3 -m venv "$venv"
    "$venv/bin/pip" install --quiet --disable-pip-version-check "kubernetes-validate==1.31.0"
fi
"$venv/bin/kubernetes-validate" --strict --kubernetes-version 1.31.0 ./*.yaml

cells="$(mktemp -d)"
trap 'rm -rf "$cells"' EXIT
"$venv/bin/python" - "$cells" ./*.yaml <<'PY'
import sys, yaml
out = sys.argv[1]
for path in sys.argv[2:]:
    for doc in yaml.safe_load_all(open(path)):
        if doc and doc.get("kind") == "ConfigMap":
            for name, text in (doc.get("data") or {}).items():
                if name.endswith(".toml"):
                    with open(f"{out}/{doc['metadata']['name']}-{name}", "w") as f:
                        f.write(text)
PY
for cell in "$cells"/*.toml; do
    "$cellgate" check-config "$cell" >/dev/null
    echo "INFO $(basename "$cell"): a valid cell file"
done
