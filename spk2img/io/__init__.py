"""The spike format: reading and writing ``(T, H, W)`` 0/1 streams (:mod:`.spikes`) and the
light convention that turns spike rates into intensity (:mod:`.light`). numpy only."""
