#!/usr/bin/env bash
# The README's test command: install tapost with its test extras, make sure a headless Chromium is there
# for the report's browser test (Debian package, best effort: needs root and apt-get), run the suite on
# every core (pytest-xdist; the tests share no files, each has its own tmp_path).
# pytest's exit 5 ("no tests collected") is a failure here.
set -uo pipefail
cd "$(dirname "$0")/.."
python -m pip install -q -e ".[test]" || exit 1
if ! command -v chromium >/dev/null 2>&1 && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "test.sh: installing Debian chromium for the HTML report test" >&2
  { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium; } >/dev/null 2>&1 \
    || echo "test.sh: chromium could not be installed; the browser test will be skipped" >&2
fi
# the numba kernels compiled once, here, rather than by every test worker on its own (about 50 s each)
python -m pipelines.warmup --quiet || echo "test.sh: the kernels could not be compiled ahead; the tests compile them" >&2
# a worker per core, one BLAS thread each, numpy without huge pages (as the CLI runs: pipelines/cli.py
# BLAS_THREADS, NUMPY_HUGEPAGES); more threads only wait
OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}" OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}" \
  MKL_NUM_THREADS="${MKL_NUM_THREADS:-1}" NUMPY_MADVISE_HUGEPAGE="${NUMPY_MADVISE_HUGEPAGE:-0}" python -m pytest -p no:cacheprovider -n auto "$@"
rc=$?
if [ "$rc" -eq 5 ]; then echo "test.sh: pytest collected no tests" >&2; exit 1; fi
exit "$rc"
