"""The rig daemon: a fixed-rate loop around the runtime layer, a rig link (simulated or serial), a
run log and a loopback API (see docs/tutorials/rig.md)."""
