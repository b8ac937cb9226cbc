"""The wire protocol of ``POST /v1/reconstruct`` responses (:mod:`.framing`), shared by the
service, which writes records, and the clients, which parse them. numpy only."""
