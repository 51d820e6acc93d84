"""The commands of ``armid`` (:mod:`armid.cli`), one module each: its options (``add_parser``)
and what it runs. Beside them what several share: the options' types and ``--robot``
(``arguments``), strict JSON and held warnings (``output``), the rig and its driver (``rig``),
the Zenoh session (``session``)."""
