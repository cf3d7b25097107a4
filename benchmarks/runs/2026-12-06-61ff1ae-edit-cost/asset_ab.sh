set -e
for round in 1 2; do
 for b in base final; do
  d=$(mktemp -d); 
  /tmp/cs-$b serve --data $d --addr 127.0.0.1:0 --demo-synthetic 2 --demo-trees 300 > $d/out 2>/dev/null &
  pid=$!; for i in $(seq 600); do [ -s $d/out ] && break; sleep 0.2; done
  port=$(head -1 $d/out | rev | cut -d: -f1 | rev)
  /work/main/target/release/canopy load http://127.0.0.1:$port/api/scenes/demo --clients 256 --duration 10 --json > /tmp/load-$b-$round.json 2>/dev/null || true
  kill $pid; wait $pid 2>/dev/null || true; rm -rf $d
  python3 -c "
import json; d=json.load(open('/tmp/load-$b-$round.json')); print('$b', $round, {k:v for k,v in d.items() if isinstance(v,(int,float)) and ('request' in k or 'error' in k or 'p99' in k or 'per_s' in k)})"
 done
done
