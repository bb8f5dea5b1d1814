#!/usr/bin/env bash
# The container test: builds the image, starts deploy/compose.yaml (a router and two cells),
# submits a job from the host through the router to a simulated cell and sees it complete,
# restarts the router and sees the gateway serve again, stops a gateway and sees it exit 0
# within 10 s with its liveliness gone. Skips, saying so, where no Docker engine answers.
#
#   deploy/container-test.sh [--profile release|dev]
set -euo pipefail
cd "$(dirname "$0")/.."

profile=release
if [ "${1:-}" = "--profile" ]; then profile="$2"; fi

if ! command -v docker >/dev/null 2>&1 || ! docker info >/dev/null 2>&1; then
    echo "container test skipped: no Docker engine answers here"
    exit 0
fi
if docker compose version >/dev/null 2>&1; then
    compose=(docker compose)
elif command -v docker-compose >/dev/null 2>&1; then
    compose=(docker-compose)
else
    echo "container test skipped: Docker has no Compose tool here"
    exit 0
fi

run_id="$$"
export CELLGATE_IMAGE="cellgate:test-$run_id"
project="cellgate-test-$run_id"
export CELLGATE_ROUTER_PORT="$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')"
dc() { "${compose[@]}" -p "$project" -f deploy/compose.yaml "$@"; }
cleanup() {
    dc down -v --timeout 5 >/dev/null 2>&1 || true
    docker rmi "$CELLGATE_IMAGE" >/dev/null 2>&1 || true
}
trap cleanup EXIT

deploy/build-image.sh --profile "$profile" --tag "$CELLGATE_IMAGE"
target="${CARGO_TARGET_DIR:-target}"
if [ "$profile" = release ]; then cellgate="$target/release/cellgate"; else cellgate="$target/debug/cellgate"; fi
endpoint="tcp/127.0.0.1:$CELLGATE_ROUTER_PORT"
step() { echo "--- $*"; }
fail() { echo "FAILED: $*" >&2; dc logs --tail 30 >&2 || true; exit 1; }

# Healthy within $2 seconds: the gateway of cell $1 answers through the router, links up.
wait_healthy() {
    local cell="$1" secs="$2" start=$SECONDS
    while ! "$cellgate" health -e "$endpoint" --cell "$cell" --timeout 3 >/dev/null 2>&1; do
        if [ $((SECONDS - start)) -ge "$secs" ]; then
            "$cellgate" health -e "$endpoint" --cell "$cell" --timeout 3 || true
            fail "cell $cell not healthy within $secs s"
        fi
        sleep 1
    done
    echo "cell $cell healthy after $((SECONDS - start)) s"
}

step "compose up: router, cell-a, cell-b (router on $endpoint)"
dc up -d
wait_healthy cell-a 90
wait_healthy cell-b 90

step "a job from the host, through the router, to mill-1 of cell-a"
program="$(mktemp)"
{
    echo "%"
    echo "O0042"
    for i in $(seq 1 200); do echo "N$i G01 X$i.000 Y-$i.500 F1200"; done
    echo "M30"
    echo "%"
} > "$program"
"$cellgate" submit -e "$endpoint" --cell cell-a mill-1 "$program" \
    || fail "the job did not complete"
rm -f "$program"

step "the router restarts; the gateways serve again"
dc restart router
wait_healthy cell-a 60
wait_healthy cell-b 60
"$cellgate" status -e "$endpoint" --cell cell-a >/dev/null || fail "no status after the restart"

step "the image's own health check runs inside the container"
container="$(dc ps -q cell-a)"
docker exec "$container" /usr/local/bin/cellgate health || fail "health inside the container"

step "Docker's health check (the image's HEALTHCHECK) says healthy"
start=$SECONDS
until [ "$(docker inspect --format '{{.State.Health.Status}}' "$container")" = healthy ]; do
    [ $((SECONDS - start)) -lt 60 ] || fail "cell-a is $(docker inspect --format '{{.State.Health.Status}}' "$container")"
    sleep 2
done
echo "cell-a: healthy"

step "cell-b stops: exit 0 within 10 s, its liveliness gone"
container="$(dc ps -q cell-b)"
start=$(date +%s%3N)
docker stop --time 10 "$container" >/dev/null
elapsed_ms=$(( $(date +%s%3N) - start ))
elapsed="$((elapsed_ms / 1000)).$(printf %03d $((elapsed_ms % 1000)))"
code="$(docker inspect --format '{{.State.ExitCode}}' "$container")"
echo "cell-b stopped in ${elapsed} s with exit code $code"
[ "$code" = 0 ] || fail "cell-b exited $code"
[ "$elapsed_ms" -lt 10000 ] || fail "cell-b took ${elapsed} s to stop"
if "$cellgate" health -e "$endpoint" --cell cell-b --gateway-only --timeout 3 >/dev/null 2>&1; then
    fail "cell-b still answers or its liveliness token stands"
fi
"$cellgate" health -e "$endpoint" --cell cell-a >/dev/null || fail "cell-a went down with cell-b"

echo "container test passed"
