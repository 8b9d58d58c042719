"""Quality control of production dampers: a short plan on the rig, identification, the
characteristics judged against a versioned spec with their uncertainty, an immutable
record in a database, and a report per unit (``python -m rig qc …``)."""

DEFAULT_SPEC = "measurands"   # qc run's spec: judged on measurands at the axle, captured from RUN on (docs/qc.md)
