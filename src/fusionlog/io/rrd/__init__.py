"""Rerun recordings (.rrd): the evaluation recordings of state and identity scenarios, and
reading them back.

- :mod:`.stream`: what every recording shares (application id, deterministic recording id,
  properties, default blueprint in the same file, the series writer) and how its bytes reach
  the disk: encoded in memory and written with Python file I/O into a file object, never
  through Rerun's file sink.
- :mod:`.state_recording`: the state-estimation recording (Figs. 4-6, consistency, sample
  runs), with :mod:`.plane` for the state-plane view of a 2-D state.
- :mod:`.identity_recording`: the identity-fusion recording (BAYES, DS).
- :mod:`.read`: :func:`read_recording`.
- :mod:`.style`, :mod:`.views`: colours and blueprint pieces.

Writers take a binary file object (a :class:`fusionlog.io.atomic.CheckedFile` from
:class:`fusionlog.io.atomic.Outputs`), never a path::

    with Outputs([out], force=force, inputs=[...]) as outs:
        write_recording(outs.open(out), scenario_name=..., ...)
        outs.commit()
"""

from .identity_recording import write_identity_recording
from .read import read_recording
from .state_recording import write_evaluation, write_recording
from .stream import APPLICATION_ID, entity_path, recording_id_for
from .style import arch_color, class_color

__all__ = [
    "APPLICATION_ID",
    "arch_color",
    "class_color",
    "entity_path",
    "read_recording",
    "recording_id_for",
    "write_evaluation",
    "write_identity_recording",
    "write_recording",
]
