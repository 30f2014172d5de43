#!/usr/bin/env bash
# Several cmr-agent replicas on this machine behind a real nginx that routes by map id with
# consistent hashing, all sharing one map directory (DESIGN §9). Shows where each region's
# requests land, that a region uploaded through one replica is served by the others, and what
# happens when a replica dies.
#
#   bash docker/local-cluster.sh [replicas=3]     (needs nginx: apt-get install nginx-light)
set -euo pipefail
cd "$(dirname "$0")/.."
replicas=${1:-3}
base_port=${BASE_PORT:-18081}
probe_base_port=${PROBE_BASE_PORT:-18181}   # replica i's probe port (/health, /ready): probe_base_port + i
proxy_port=${PROXY_PORT:-18080}
bin=./target/release/cmr-agent
command -v nginx >/dev/null || { echo "nginx not found: apt-get install nginx-light" >&2; exit 1; }
[ -x "$bin" ] || cargo build --release
bash scripts/install-onnxruntime.sh

work=$(mktemp -d /tmp/cmr-cluster.XXXXXX)
chmod 755 "$work"   # nginx workers (an unprivileged user) buffer request bodies in here
pids=()
cleanup() {
    [ -f "$work/nginx.pid" ] && kill "$(cat "$work/nginx.pid")" 2>/dev/null || true
    for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done
    wait 2>/dev/null || true
    [ -n "${KEEP:-}" ] || rm -rf "$work"
}
trap cleanup EXIT

mkdir -p "$work/maps" "$work/logs"
cp maps/demo.bin maps/demo.json "$work/maps/"   # the shared map directory
upstreams=""
for i in $(seq 0 $((replicas - 1))); do
    port=$((base_port + i))
    CMR_HOST=127.0.0.1 CMR_PORT=$port CMR_PROBE_PORT=$((probe_base_port + i)) CMR_MAPS="$work/maps" CMR_INTRA_THREADS=1 \
        "$bin" serve > "$work/logs/replica-$i.log" 2>&1 &
    pids+=($!)
    upstreams+="    server 127.0.0.1:$port max_fails=1 fail_timeout=10s;"$'\n'
done
sed -e "s|@LISTEN@|127.0.0.1:$proxy_port|" docker/nginx.conf.template |
    awk -v ups="$upstreams" '{ if ($0 == "@UPSTREAMS@") printf "%s", ups; else print }' > "$work/nginx-site.conf"
cat > "$work/nginx.conf" <<CONF
pid $work/nginx.pid;
error_log $work/logs/nginx-error.log;
events {}
http {
    access_log $work/logs/nginx-access.log;
    client_body_temp_path $work/body;
    proxy_temp_path $work/proxy;
    include $work/nginx-site.conf;
}
CONF
for i in $(seq 0 $((replicas - 1))); do
    until curl -sf --max-time 1 "http://127.0.0.1:$((probe_base_port + i))/ready" >/dev/null; do sleep 0.2; done
done
nginx -c "$work/nginx.conf" -p "$work"
echo "replicas ready on ports $base_port..$((base_port + replicas - 1)) (probes on $probe_base_port..$((probe_base_port + replicas - 1))); nginx on $proxy_port"

proxy="http://127.0.0.1:$proxy_port"
# localize ID [curl options]: the demo request through the proxy.
localize() {
    local id=$1; shift
    curl -s "$@" -H 'content-type: application/json' --data-binary @examples/localize-demo.json "$proxy/v1/maps/$id/localize"
}
upstream_of() { tr -d '\r' | awk 'tolower($1) == "x-cmr-upstream:" { $1 = ""; sub(/^ /, ""); print }'; }
echo
echo "== register four regions through the proxy (each lands on its ring owner) =="
for id in region-a region-b region-c region-d; do
    up=$(curl -s -D - -o /dev/null -X PUT --data-binary @maps/demo.bin "$proxy/v1/maps/$id?format=kitti_bin" | upstream_of)
    echo "$id -> $up"
done
echo
echo "== localize each region three times: always the same replica =="
for id in demo region-a region-b region-c region-d; do
    ups=$(for _ in 1 2 3; do
        localize "$id" -D - -o /dev/null | upstream_of
    done | sort -u | tr '\n' ' ')
    echo "$id -> $ups"
done
echo
echo "== every replica lists every region (shared directory) =="
for i in $(seq 0 $((replicas - 1))); do
    echo "replica $i: $(curl -s "http://127.0.0.1:$((base_port + i))/v1/maps" | python3 -c 'import json,sys; print(sorted(m["id"] for m in json.load(sys.stdin)["maps"]))')"
done
echo
victim_port=$(localize region-a -D - -o /dev/null | upstream_of | sed 's/.*://')
echo "== stop the replica that owns region-a (port $victim_port) and localize region-a again =="
for i in "${!pids[@]}"; do
    if [ $((base_port + i)) = "$victim_port" ]; then kill "${pids[$i]}"; wait "${pids[$i]}" 2>/dev/null || true; fi
done
for _ in 1 2; do
    localize region-a -D "$work/headers.txt" -o "$work/response.json" || true
    echo "status $(head -1 "$work/headers.txt" | awk '{print $2}'), upstream $(upstream_of < "$work/headers.txt"), iterations $(python3 -c 'import json,sys; print(json.load(open(sys.argv[1])).get("iterations"))' "$work/response.json")"
done
