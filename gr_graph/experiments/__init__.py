"""The experiment harness of the paper's tables (issue 10, item 2): Table I, Table II, ablations.

One resumable command per table; each cell is its own resumable run in
``ROOT/<table>/<cell-key>/`` that can also be launched alone, so a cluster scheduler can
spread the cells over machines::

    python -m gr_graph.experiments table1 --list                 # index, key, what, estimated minutes on 2 cores
    python -m gr_graph.experiments table1 --root runs/exp        # every unfinished cell in order, then the report
    python -m gr_graph.experiments table1 --root runs/exp --cell 3   # one cell (index or key)
    python -m gr_graph.experiments table1 --root runs/exp --report --publish   # report only -> benchmarks/results

A SLURM array (one cell per task; Table II needs Table I's cells, the ablations' reusing
cells prefer their default cell finished first, otherwise they compute everything themselves;
the array sizes are the ``paper`` budget's, ``--list`` gives another budget's)::

    sbatch --array=0-7 --cpus-per-task=2 --mem=8G --wrap \\
        'python -m gr_graph.experiments table1 --root $SCRATCH/exp --cell $SLURM_ARRAY_TASK_ID'
    sbatch --dependency=afterok:<table1 job id> --array=0-19 --cpus-per-task=2 --wrap \\
        'python -m gr_graph.experiments table2 --root $SCRATCH/exp --cell $SLURM_ARRAY_TASK_ID'
    python -m gr_graph.experiments table1 --root $SCRATCH/exp --report --publish   # when all are done

Modules: :mod:`~gr_graph.experiments.cells` (cell definitions and budgets, pure data),
:mod:`~gr_graph.experiments.revisits` (windows with a revisit), :mod:`~gr_graph.experiments.run_cell`
(one cell: resume, reuse, pruning), :mod:`~gr_graph.experiments.cell_lock` (one process a cell), :mod:`~gr_graph.experiments.kiss_baseline` (KISS-ICP on the
same scans), :mod:`~gr_graph.experiments.aggregate` (mean ± std, reductions),
:mod:`~gr_graph.experiments.figures`, :mod:`~gr_graph.experiments.report`,
:mod:`~gr_graph.experiments.records` (published cell records: a report combines cells run in
different roots), :mod:`~gr_graph.experiments.cli`.
"""
