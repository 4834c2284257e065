"""evgrid's lab: the programs that run evgrid on its simulator, for the command line:
``evgrid bench`` (:mod:`evgrid_lab.bench`), ``evgrid transfer`` (:mod:`evgrid_lab.transfer`)
and the options of ``evgrid simulate`` and ``evgrid bench`` (:mod:`evgrid_lab.options`).

It stands above both packages: it imports evgrid's mapper, runs and sources and the simulator
``evgrid_sim``; neither imports it, and only ``evgrid.cli`` does.
"""
