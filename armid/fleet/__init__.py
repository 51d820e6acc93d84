"""A lab's fleet (issue 37): every recording of every arm identified, quantities tracked over
time, changes found.

- :mod:`armid.fleet.discover`: ``ROOT/<arm>/robot.yaml`` and each arm's recordings;
- :mod:`armid.fleet.task`: one recording through :mod:`armid.pipeline` (what ``armid
  identify`` runs), cross-validated, its tracked quantities (:mod:`armid.identify.tracked`);
- :mod:`armid.fleet.engine`: Ray tasks (the optional extra ``armid[fleet]``) or this process;
- :mod:`armid.fleet.outputs`: ``parameters.csv``, change detection (:mod:`armid.identify.changes`),
  ``changes.json``;
- :mod:`armid.fleet.report`: ``report.md`` with a trend plot per change;
- :mod:`armid.fleet.command`: ``armid fleet`` itself.
"""
