"""The fleet: the agent's local protocol to the bridge process (``local_protocol``), the network payloads
(``payloads``), the bridge itself (``bridge``: the agent's Unix socket <-> Zenoh) and the fleet view
(``view``). The agent process imports only ``local_protocol``; Zenoh is imported by the bridge and the view,
which run in their own processes (docs/fleet.md)."""
