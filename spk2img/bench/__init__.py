"""``spk2img bench``: speed against error for every reconstruction method, in one command.

:mod:`.cases` is the fixed simulated benchmark set, :mod:`.rows` the methods behind one
interface, :mod:`.worker` measures one row in a fresh process, :mod:`.timing` the timers,
:mod:`.service_load` the HTTP service under load, :mod:`.runner` ties them together and
:mod:`.report` writes ``bench.md``, ``bench.json`` and the Pareto plot.
"""
