"""OpenIGTLink: the protocol (:mod:`.protocol`) and the bridge to the API (:mod:`.bridge`)."""
