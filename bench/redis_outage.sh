#!/usr/bin/env bash
# Issue 44's Redis fault at production timings (the live test, tests/service/test_faults.py, runs the same paths
# at a fifth of them): `dualphys serve` with its defaults (60 s run lock, 15 min visibility, 12 s watchdog grace)
# against a redis-server of its own, a fast job on a generated 12-view 160x120 scene, Redis shut down at the
# first training checkpoint for OUTAGE seconds and started again. Prints the job's status every 5 s and, at the
# end, each stage's attempts and outcomes: the job should end `done`, once, training never resumed.
#
#   bash bench/redis_outage.sh aof|none [OUT] [OUTAGE=60] [ITERATIONS=2500]
#
# aof: append-only persistence (Redis comes back with its queues, locks expired); none: Redis comes back empty.
set -u
MODE=${1:?aof or none}; OUT=${2:-/tmp/dualphys-redis-outage}; OUTAGE=${3:-60}; ITER=${4:-2500}
REPO=$(cd "$(dirname "$0")/.." && pwd); V=$REPO/.venv/bin
B=$OUT/$MODE; rm -rf "$B"; mkdir -p "$B/redis" "$B/data"
PORT=$((6390 + RANDOM % 500)); API=$((8790 + RANDOM % 500)); KEY=outage-bench-key-0123456789
[ -d "$OUT/scene/images" ] || "$V/dualphys" synth --out "$OUT/scene" --views 12 --size 160x120 --preset medium --seed 0
persist=no; [ "$MODE" = aof ] && persist=yes
redis_start() { redis-server --port $PORT --bind 127.0.0.1 --dir "$B/redis" --appendonly $persist --save '' \
                             --daemonize yes --logfile "$B/redis/log"; sleep 0.5; }
redis_start
echo "{\"$KEY\": \"local\"}" > "$B/keys.json"
OMP_WAIT_POLICY=PASSIVE setsid "$V/dualphys" serve --port $API --data-dir "$B/data" \
  --redis-url redis://127.0.0.1:$PORT/0 --api-keys-file "$B/keys.json" --no-beat > "$B/serve.log" 2>&1 &
SERVE=$!
trap 'kill -TERM -$SERVE 2>/dev/null; sleep 3; redis-cli -p $PORT shutdown nosave >/dev/null 2>&1' EXIT
for _ in $(seq 120); do curl -sf http://127.0.0.1:$API/ready >/dev/null && break; sleep 1; done
JID=$("$V/dualphys" submit --server http://127.0.0.1:$API --key $KEY "$OUT/scene/images" --preset fast \
      --iterations "$ITER" --mode 3dgs 2>&1 | grep -oE 'j[0-9a-f]{21}' | head -1)
echo "job $JID"
st() { curl -s -H "Authorization: Bearer $KEY" http://127.0.0.1:$API/v1/jobs/$JID | python3 -c \
       'import sys,json; d=json.load(sys.stdin); print(d["state"], d["stage"], "lost" if d["worker_lost"] else "-", d["message"][:100])'; }
t0=$(date +%s)
until grep -q "checkpoint written" "$B/data/jobs/$JID/log.txt" 2>/dev/null; do
  sleep 0.5; [ $(( $(date +%s) - t0 )) -gt 900 ] && { echo "no checkpoint in 900 s"; exit 1; }; done
echo "$(date +%T) checkpoint written; Redis shut down for $OUTAGE s"
redis-cli -p $PORT shutdown nosave >/dev/null 2>&1
stop=$(date +%s)
while [ $(( $(date +%s) - stop )) -lt "$OUTAGE" ]; do echo "+$(( $(date +%s) - stop )) s  $(st)"; sleep 5; done
redis_start; back=$(date +%s); echo "$(date +%T) Redis back"
for i in $(seq 900); do
  S=$(st); [ $((i % 5)) = 1 ] && echo "back +$(( $(date +%s) - back )) s  $S"
  case "$S" in done*|failed*|cancelled*) echo "ended: $S"; break;; esac; sleep 1; done
curl -s -H "Authorization: Bearer $KEY" http://127.0.0.1:$API/v1/jobs/$JID | python3 -c '
import sys, json; d = json.load(sys.stdin)
print("state", d["state"], "completed_runs", d["completed_runs"])
for s in d["stages"]: print(" ", s["name"], s["status"], "attempts", s["attempts"], [a["outcome"] for a in s["history"]])'
echo "training resumed from a checkpoint: $(grep -c 'resumed from' "$B/data/jobs/$JID/log.txt") times;" \
     "later stages started: $(grep -cE 'stage (evaluate|restore|survey|export) started' "$B/data/jobs/$JID/log.txt") (4 = once each)"
