"""The command lines: ``dhg`` (:mod:`~dhg.cli.main`, its offline commands in
:mod:`~dhg.cli.commands`, those that talk to a server in :mod:`~dhg.cli.live`), ``dhg-serve``
(:mod:`~dhg.cli.serve`), ``dhg live-demo`` (:mod:`~dhg.cli.demo`, the whole product on one machine)
and what they share (:mod:`~dhg.cli.common`)."""
