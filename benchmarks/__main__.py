"""
Run every benchmark module (or those named on the command line) and print one JSON object.

Benchmarks measure and report; they never assert timings (the tests do not either).
"""

import argparse
import importlib
import json
import os
import pkgutil
import sys
import time
import traceback

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('ROS_DOMAIN_ID', str(os.getpid() % 100 + 101))

from softshape_ros.transport import configure_transport  # noqa: E402

# Every benchmark process talks DDS the way the nodes do (the shipped profile unless the
# environment says otherwise); bench_transport sets it per case to compare.
configure_transport()

import benchmarks  # noqa: E402


def main(argv=None) -> int:
    names = sorted(m.name for m in pkgutil.iter_modules(benchmarks.__path__)
                   if m.name.startswith('bench_'))
    parser = argparse.ArgumentParser(prog='python -m benchmarks')
    parser.add_argument('only', nargs='*', help=f'subset of: {", ".join(names)}')
    args = parser.parse_args(argv)
    results, failed = {}, False
    for name in names:
        if args.only and name not in args.only and name[len('bench_'):] not in args.only:
            continue
        t0 = time.perf_counter()
        try:
            results[name] = importlib.import_module(f'benchmarks.{name}').run()
        except Exception as exc:  # report, keep going, exit non-zero at the end
            traceback.print_exc()
            results[name] = {'error': f'{type(exc).__name__}: {exc}'}
            failed = True
        results[name]['wall_s'] = round(time.perf_counter() - t0, 2)
        print(f'# {name} done in {results[name]["wall_s"]} s', file=sys.stderr)
    print(json.dumps(results, indent=2))
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())
