"""Studies (researchers): the in-process simulated fleet (``fleet``), the Monte Carlo runner
(``runner``) and its value types (``types``, at the bottom), the UFastSLAM study (``ufastslam``),
Dask clusters (``cluster``) and shards (``shards``), the results archive (``archive``), the
report and plots (``report``, ``plots``), the paper's read-off values (``paper_figures``),
classifier fits (``classifier_*``), scenario pictures (``scenario_show``) and the TUM export
(``tum``). It imports ``deploy.base`` only of ``deploy``."""
