"""A module written the way the original CAVIAR wrote them: a plain NATS client that
speaks JSON on the paper's subjects and knows nothing of caviar.

It listens to ``3D.mobility.positions`` and answers every position with a
free-space throughput estimate on ``communications.throughput``. To take part in a
run with ``transport.kind = "nats"``:

* the core mirrors every data message onto its own subject (``transport.nats.mirror``,
  default all), so this script receives the positions as the original did;
* a ``caviar.nats-bridge`` module brings ``communications.throughput`` back into the
  episode; ``wait_for = 1`` makes it wait for the answer, which keeps this free-running
  script in lockstep with virtual time.

    python examples/legacy_caviar_module.py nats://127.0.0.1:4222

(blueprints/legacy/config.toml is the config; tests/test_nats.py runs it.)
"""

import asyncio
import json
import math
import sys

import nats

TX = (-154.0, 64.0, 120.0)   # the paper's rooftop base station (m)
WAVELENGTH = 3e8 / 40e9      # 40 GHz
BANDWIDTH_HZ = 40e6
SNR_AT_1M = 1e12             # transmit power x array gains / noise, a round number


def throughput_mbps(position: dict) -> float:
    d = math.dist(TX, (position["x"], position["y"], position["z"]))
    path_gain = (WAVELENGTH / (4 * math.pi * d)) ** 2
    return BANDWIDTH_HZ * math.log2(1 + SNR_AT_1M * path_gain * (4 * math.pi) ** 2 / WAVELENGTH**2) / 1e6


async def main(url: str) -> None:
    nc = await nats.connect(url)

    async def on_position(msg):
        ue = json.loads(msg.data)
        answer = {"UE_type": ue["UE_type"], "UE_Id": ue["UE_Id"], "throughput": throughput_mbps(ue["position"])}
        await nc.publish("communications.throughput", json.dumps(answer).encode())

    await nc.subscribe("3D.mobility.positions", cb=on_position)
    await nc.flush()
    print("legacy module ready", flush=True)
    await asyncio.Event().wait()


if __name__ == "__main__":
    asyncio.run(main(sys.argv[1] if len(sys.argv) > 1 else "nats://127.0.0.1:4222"))
