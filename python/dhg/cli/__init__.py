"""The command lines: ``dhg`` (:mod:`~dhg.cli.main`), ``dhg-serve`` and the live subcommands
(:mod:`~dhg.cli.serve`), and what they share (:mod:`~dhg.cli.common`)."""
