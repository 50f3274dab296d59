#!/usr/bin/env bash
# A scheduled weldrecon service on one machine: a Prefect server on 127.0.0.1, the process work
# pool `weldrecon`, the deployments of deploy/prefect.yaml and one worker.
#
#   deploy/service.sh up      start server + pool + deployments + worker (background, logs in $STATE)
#   deploy/service.sh down    stop the worker and the server
#   deploy/service.sh status  what runs
#
# Settings (environment): WELDRECON_WORKSPACE (catalog and run folders, default ./workspace),
# WELDRECON_SAMPLES (folder of sample folders the nightly batch scans, default ./samples),
# WELDRECON_PORT (server port, default 4200). State (Prefect's database, pid files, logs) lives in
# $WELDRECON_WORKSPACE/service.
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
PY="$ROOT/.venv/bin"
export WELDRECON_ROOT="$ROOT"
export WELDRECON_WORKSPACE="$(realpath -m "${WELDRECON_WORKSPACE:-$ROOT/workspace}")"
export WELDRECON_SAMPLES="$(realpath -m "${WELDRECON_SAMPLES:-$ROOT/samples}")"
PORT="${WELDRECON_PORT:-4200}"
STATE="$WELDRECON_WORKSPACE/service"
export PREFECT_HOME="$STATE/prefect"
export PREFECT_API_URL="http://127.0.0.1:$PORT/api"
export PREFECT_SERVER_ANALYTICS_ENABLED=false
export PREFECT_WORKER_QUERY_SECONDS="${PREFECT_WORKER_QUERY_SECONDS:-10}"
mkdir -p "$STATE" "$WELDRECON_SAMPLES"

running() { [[ -f "$STATE/$1.pid" ]] && kill -0 "$(cat "$STATE/$1.pid")" 2>/dev/null; }

# start NAME CMD...: CMD in a new session (its pid is the group id `down` kills), detached from
# this script's stdin/stdout/stderr, logging to $STATE/NAME.log
start() {
  local name="$1"; shift
  setsid bash -c 'echo $$ >"$0"; exec "$@"' "$STATE/$name.pid" "$@" </dev/null >"$STATE/$name.log" 2>&1 &
  for _ in $(seq 1 50); do [[ -s "$STATE/$name.pid" ]] && return 0; sleep 0.1; done
}

wait_for_server() {
  for _ in $(seq 1 180); do
    if "$PY/python" -c "import urllib.request,sys; urllib.request.urlopen('$PREFECT_API_URL/health', timeout=2)" 2>/dev/null; then
      return 0
    fi
    running server || { echo "the Prefect server exited; see $STATE/server.log" >&2; return 1; }
    sleep 1
  done
  echo "the Prefect server did not answer on $PREFECT_API_URL within 180 s" >&2
  return 1
}

up() {
  cd "$ROOT"
  if ! running server; then
    start server "$PY/prefect" server start --host 127.0.0.1 --port "$PORT"
  fi
  wait_for_server
  "$PY/prefect" work-pool inspect weldrecon >/dev/null 2>&1 || "$PY/prefect" work-pool create weldrecon --type process
  "$PY/prefect" --no-prompt deploy --all --prefect-file deploy/prefect.yaml </dev/null
  if ! running worker; then
    start worker "$PY/prefect" worker start --pool weldrecon --limit 1
  fi
  echo "weldrecon service up: UI http://127.0.0.1:$PORT, workspace $WELDRECON_WORKSPACE, samples $WELDRECON_SAMPLES"
}

down() {
  for name in worker server; do
    if running "$name"; then
      pid="$(cat "$STATE/$name.pid")"
      kill -- "-$pid" 2>/dev/null || kill "$pid" 2>/dev/null || true
      for _ in $(seq 1 150); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
      kill -9 -- "-$pid" 2>/dev/null || kill -9 "$pid" 2>/dev/null || true
    fi
    rm -f "$STATE/$name.pid"
  done
  echo "weldrecon service down"
}

status() {
  for name in server worker; do
    if running "$name"; then echo "$name: running (pid $(cat "$STATE/$name.pid"))"; else echo "$name: stopped"; fi
  done
}

case "${1:-}" in
  up) up ;;
  down) down ;;
  status) status ;;
  *) echo "usage: $0 up|down|status" >&2; exit 2 ;;
esac
