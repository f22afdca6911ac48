"""The material constants the FEM takes, once: the Neo-Hookean law refuses others
(``fem/material.py``, and so a store entry's manifest), as do a scene's [material] table
(``scene/tables.py``) and a session's E (``api/work.py``).

Soft tissue's E runs from 100 Pa (brain) to 10 MPa (cartilage) and its nu from 0.45 to 0.499:
two decades of margin each. Outside them the FEM cannot solve the first load steps.
"""

E_RANGE = (1.0, 1e12)  # Pa
NU_RANGE = (0.0, 0.49999)
