"""Move the jammer of a running system, as `jamnav jammer set X,Y,P` does (or `off`, `show`).

    python examples/move_jammer.py --connect tcp/127.0.0.1:7447 25,-10,1
"""

import argparse
import sys

from jamnav.arguments import jammer_command
from shared import bus
from shared.jammer_messages import JammerReply, describe_jammers, jammer_numbers
from shared.topics import Topics, endpoint_from

parser = argparse.ArgumentParser(prog="move_jammer", description=__doc__.splitlines()[0])
parser.add_argument("--connect", "-e", metavar="ENDPOINT", help="the system's router")
parser.add_argument("--prefix", default="jamnav", help="the system's key prefix")
parser.add_argument("jammer", metavar="X,Y,P[,H]|off|show", help="where to (metres, watts)")
args = parser.parse_args()

# The command the CLI sends: a JammerCommand query on the world's control key.
action = args.jammer if args.jammer in ("off", "show") else "set"
numbers = jammer_numbers(args.jammer) if action == "set" else None
command = jammer_command(action, numbers, args.jammer)
with bus.open_session("client", endpoint_from(args.connect)) as session:
    reply = bus.query(session, Topics(args.prefix).jammer_control, JammerReply, command)
# The world applies a jammer it accepts between steps; the reply names the step.
print(f"{'accepted' if reply.accepted else f'refused ({reply.reason})'}: "
      f"{describe_jammers(reply.jammers)} (episode {reply.episode}, step {reply.step})")
sys.exit(0 if reply.accepted else 2)
