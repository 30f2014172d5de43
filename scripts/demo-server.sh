# Sourced by scripts that need a live server: `start_demo_server [serve flags...]` starts
# target/release/cmr-agent on a free loopback port with a temporary copy of the demo map, sets
# `port`, stops the server and removes the copy when the calling script exits, and returns once
# /ready answers (at most 60 s).
start_demo_server() {
  maps=$(mktemp -d)
  cp maps/demo.bin maps/demo.json "$maps"/
  port=$((20000 + RANDOM % 10000))
  ./target/release/cmr-agent serve --host 127.0.0.1 --port "$port" --maps "$maps" "$@" 2>"$maps/server.log" &
  server=$!
  trap 'kill $server 2>/dev/null; wait $server 2>/dev/null; rm -rf "$maps"' EXIT
  for _ in $(seq 1 300); do
    curl -fs "http://127.0.0.1:$port/ready" >/dev/null 2>&1 && return 0
    sleep 0.2
  done
}
