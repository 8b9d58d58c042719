"""Quality control of production dampers: a short plan on the rig, identification, the
characteristics judged against a versioned spec with their uncertainty, an immutable
record in a database, and a report per unit (``python -m rig qc …``)."""

# qc run's spec.  The measurand spec (`--spec measurands`: judged at the axle, captured from
# RUN on) is shipped beside it but not yet the default: its confusion table and served rig
# time have not been measured on the merged plant (end stops, one integration grid).
DEFAULT_SPEC = "default"
