"""Node runtime: bus (zenoh or in-process), node contract and runner, config loading."""

from constructaide.runtime.bus import Bus, BusConfig, Collector, ZenohBus, add_bus_args, open_bus
from constructaide.runtime.node import (
    Input,
    NodeContext,
    NodeSpec,
    Output,
    RunningNode,
    add_node_args,
    load_config,
    run_node_cli,
    start_node,
)

__all__ = [
    "Bus",
    "BusConfig",
    "Collector",
    "ZenohBus",
    "add_bus_args",
    "open_bus",
    "Input",
    "NodeContext",
    "NodeSpec",
    "Output",
    "RunningNode",
    "add_node_args",
    "load_config",
    "run_node_cli",
    "start_node",
]
