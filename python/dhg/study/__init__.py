"""``dhg study``: guided against unguided training of virtual novices, with paired statistics:
what is compared (:mod:`~dhg.study.design`), how the attempts run (:mod:`~dhg.study.runner`) and
what they showed (:mod:`~dhg.study.result`)."""
