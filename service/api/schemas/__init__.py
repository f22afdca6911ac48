"""The API's bodies as pydantic models, a module per resource: what a request may hold, and
what a reply holds (:mod:`.sessions`: sessions and their frames; :mod:`.models`: the store's
models and the forward problem; :mod:`.health`: the server's health and limits), on the arrays
(:mod:`.arrays`) and bases (:mod:`.common`) they share.

Requests are validated strictly (no "5" for 5, no 5.0 for a node id, no unknown keys): a body
that does not fit is a 422 whose ``detail`` names the field and what is wrong. Arrays arrive as
nested lists (JSON or MessagePack) or packed arrays (MessagePack, see :mod:`..codec`) and leave
validation as NumPy arrays: one ``np.asarray`` per array, checked for shape, dtype and
finiteness, never an element at a time.

Reply models document the replies (``/docs``, ``/openapi.json``) and let tests check them; the
routes encode replies directly (arrays as packed bytes or lists) rather than through them, so a
large displacement field does not pass through pydantic.
"""
