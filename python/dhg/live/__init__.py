"""Everything on Zenoh: the Zenoh configuration (:mod:`~dhg.live.zenoh_config`), the model and
X-ray services (:mod:`~dhg.live.services`), ``dhg-serve``'s runner (:mod:`~dhg.live.runner`), the
trainee client (:mod:`~dhg.live.client`, :mod:`~dhg.live.trainee`), the recorders
(:mod:`~dhg.live.recorder`, :mod:`~dhg.live.session_recorder`, :mod:`~dhg.live.streams`), the
secure lab mode (:mod:`~dhg.live.lab`) and ``dhg-serve`` as a child process
(:mod:`~dhg.live.process`). The engine itself is :class:`dhg.Server`. Nothing here imports
:mod:`dhg.view` or :mod:`dhg.cli`: they are clients of it."""
