"""Watch a running system: a line for each world step, SINR map and jammer estimate.

Start one (`jamnav up --uavs 4 --realtime`), then: python examples/watch.py --count 20
"""

import argparse
import queue
import sys

from shared import bus
from shared.cloud_messages import SinrMap
from shared.jammer_messages import JammerEstimate, describe_estimate
from shared.topics import Topics, endpoint_from
from shared.wire import decode
from shared.world_messages import WorldState

parser = argparse.ArgumentParser(prog="watch", description=__doc__.splitlines()[0])
parser.add_argument("--connect", "-e", metavar="ENDPOINT", help="the system's router")
parser.add_argument("--prefix", default="jamnav", help="the system's key prefix")
parser.add_argument("--count", type=int, default=0, help="stop after N lines (0: Ctrl-C)")
args = parser.parse_args()
topics = Topics(args.prefix)
# The keys watched, each with its message and the line one of them makes.
SHOWN = {
    topics.state: (WorldState, lambda s: f"world: episode {s.episode} step {s.step}, "
                   f"{s.status.count('active')} flying, jammers " + ("; ".join(
                       f"{j.id} at ({j.x:g}, {j.y:g}){'' if j.on else ' off'}"
                       for j in s.jammer_places) or "none")),
    topics.sinr_map: (SinrMap, lambda m: f"cloud: SINR map v{m.version} ({m.mode})"),
    topics.jammer_estimate: (JammerEstimate, lambda e: f"cloud: {describe_estimate(e)}"),
}

samples = queue.Queue()  # zenoh's threads put what arrives; the main thread prints in order
with bus.open_session("client", endpoint_from(args.connect)) as session:
    subscribers = [session.declare_subscriber(key, samples.put) for key in SHOWN]
    for _ in range(args.count or sys.maxsize):
        sample = samples.get()
        kind, line = SHOWN[str(sample.key_expr)]
        print(line(decode(kind, sample.payload.to_bytes())), flush=True)
