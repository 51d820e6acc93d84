"""What the declared model lacks, and whether a model still holds on new data.

The residual of a fit is searched against a catalogue of effects a rigid-body model leaves out
(friction laws, cogging, springs, drive gains, a load on the last link): ``search`` runs the
search and its gates, ``candidates`` is the catalogue, ``data`` the data as the search sees
them, ``scoring`` a round's fit, ``validation`` the held-out judgement, ``refit`` the model with
its findings, ``report`` what they say, and ``check`` holds an identified model fixed on new data.
"""
