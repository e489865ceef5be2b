"""``dhg study``: guided against unguided training of virtual novices, with paired statistics
(:mod:`~dhg.study.runner`)."""
