"""``endowave-cl batch MANIFEST``: many scenes, each through the stages flow / train / eval / render /
export, on a local Ray instance, a Ray cluster or a plain process pool, with a dataset-level report.

* ``manifest``  reads and checks the TOML manifest (one-line errors naming the file and key);
* ``tasks``     one (scene, stage) task: the command line of the existing command, completion read
                from the run folder's files, and ``run_task``, which a worker executes;
* ``executors`` where tasks run: Ray (retries a task whose worker died) or a process pool (same);
* ``runner``    the scheduler: stage order per scene, skip what is complete, progress lines;
* ``report``    ROOT/report.md, report.json and report.csv, built from the run folders' files.

See docs/BATCH.md.
"""
