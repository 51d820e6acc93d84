"""A load on the last link: on-line recursive least squares while the arm works (Khosla's on-line
strategy, eq. 18), and a change of load read from two identifications.

``rls`` is the estimator, ``filter`` the derivatives on the records' own stamps, ``arm`` the
identified arm it subtracts, ``band`` the mass's band from the arm's model error, ``projection``
the physically possible bodies, ``load_change`` a load's mass from base-parameter sums.
"""
