"""Demonstration datasets: the on-disk format, writer and reader (:mod:`~dhg.data.dataset`),
synthetic demonstrations (:mod:`~dhg.data.synth`), ``dhg inspect`` (:mod:`~dhg.data.report`) and
its plots (:mod:`~dhg.data.plots`)."""
