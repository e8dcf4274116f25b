"""A node module that takes long to load, as one importing PyTorch or Open3D does, so that a
stop finds it still loading."""

from __future__ import annotations

import time

from fixture_nodes import CounterNode

from bus.node import run_node

print("importing", flush=True)
time.sleep(60)

if __name__ == "__main__":
    run_node(CounterNode)
