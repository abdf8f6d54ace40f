"""Read an MCAP recording of a run: its events as lines, then how many messages each key got.

    jamnav up --uavs 2 --episodes 1 --record run.mcap --no-web
    python examples/read_recording.py run.mcap
"""

import argparse
from collections import Counter

from jamnav.event_lines import describe_event
from jamnav.recording import Recording

parser = argparse.ArgumentParser(prog="read_recording", description=__doc__.splitlines()[0])
parser.add_argument("path", help="an MCAP file that `jamnav up --record` or `jamnav record` wrote")
args = parser.parse_args()

counts = Counter()
with Recording(args.path) as recording:
    # Each message comes decoded (the model of its key), with its payload and its time.
    for item in recording.messages():
        counts[item.key] += 1
        if item.key.startswith(f"{recording.prefix}/event/"):
            event = item.message.model_dump(mode="json")
            # The supervisor's line for an event; the outcomes and the run's end as they are.
            line = describe_event(event) or f"{event['type']}: " + ", ".join(
                f"{name} {value}" for name, value in event.items()
                if name not in ("type", "t", "source"))
            print(f"{item.log_time_ns / 1e9:.3f} {line}")
for key, count in sorted(counts.items()):
    print(f"{count:6d} {key}")
