#!/usr/bin/env bash
# Regenerate sample_logs/: a small simulated ship pair (120 s, latency 0.1 s, drift 20 ppm,
# mounting 0.3,0.4,-1 deg, seed 1) with its truth.json.
#   bash scripts/make_sample_logs.sh                      # MCAP master + MAVLink tlog slave (default)
#   MASTER_FORMAT=csv SLAVE_FORMAT=csv bash scripts/make_sample_logs.sh
# Rates are kept low (100 Hz IMU, 50 Hz nav) so that each file stays well under 5 MB.
set -euo pipefail
cd "$(dirname "$0")/.."
out=sample_logs
mkdir -p "$out"
rm -f "$out"/master.* "$out"/slave.* "$out"/truth.json
tapost simulate ship -o "$out" --duration 120 --seed 1 \
    --latency 0.1 --drift 20 --mount 0.3,0.4,-1 \
    --master-rate 100 --master-nav-rate 50 --slave-rate 100 --slave-nav-rate 50 \
    --master-format "${MASTER_FORMAT:-mcap}" --slave-format "${SLAVE_FORMAT:-tlog}"
ls -l "$out"
