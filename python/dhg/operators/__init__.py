"""Who drives the drill: virtual surgeons' styles (:mod:`~dhg.operators.styles`), one attempt
through an offline session and its skill metrics (:mod:`~dhg.operators.episodes`), the operator
models of guidance studies and learning across attempts (:mod:`~dhg.operators.models`), and
operators without human behaviour (:mod:`~dhg.operators.scripted`). The surgeon's 1 kHz step is
the core's (:class:`dhg.core.surgeon.SurgeonController`)."""
