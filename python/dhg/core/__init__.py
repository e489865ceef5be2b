"""The one layer over the native core (``dhg._bone_sim``, Rust): only the modules here import it.

- :mod:`~dhg.core.errors`: the exception classes the core raises;
- :mod:`~dhg.core.features`, :mod:`~dhg.core.layers`, :mod:`~dhg.core.protocol`: facts the core
  defines (record columns and tick, bone layers, wire layouts, flags and the session-id rule);
- :mod:`~dhg.core.path`: the planned path A → B and the task's rules;
- :mod:`~dhg.core.skill`: the skill metrics of an attempt (the server's and ``dhg record``'s too);
- :mod:`~dhg.core.volume`: :class:`~dhg.core.volume.Volume` and its drilled copy;
- :mod:`~dhg.core.session`: :class:`~dhg.core.session.DrillingSession`, the 1 kHz simulation offline;
- :mod:`~dhg.core.surgeon`: the virtual surgeon's native 1 kHz controller and its style;
- :mod:`~dhg.core.server`: :class:`~dhg.core.server.Server`, the real-time engine on Zenoh;
- :mod:`~dhg.core.version`: this build's version.
"""
