"""OpenIGTLink: the protocol (:mod:`.protocol`) and the bridge to the API (:mod:`.bridge`, over
:mod:`.connection`, :mod:`.relay` and :mod:`.answers`)."""
