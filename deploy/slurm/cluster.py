"""A SLURM cluster for large area jobs (dask-jobqueue; `pip install dask-jobqueue`).

    python deploy/slurm/cluster.py 16       # starts 16 single-core worker jobs, prints the address
    swathflow run MISSION --out DIR --dask-address tcp://...

Workers need swathflow installed (the same environment on a shared file system).
"""
import sys
import time

from dask_jobqueue import SLURMCluster

cluster = SLURMCluster(
    queue="normal",
    cores=1,
    processes=1,
    memory="4GB",
    walltime="04:00:00",
    local_directory="$TMPDIR",
    job_extra_directives=["--job-name=swathflow-dask"],
)
cluster.scale(jobs=int(sys.argv[1]) if len(sys.argv) > 1 else 8)
print(cluster.scheduler_address, flush=True)
try:
    while True:
        time.sleep(3600)
except KeyboardInterrupt:
    cluster.close()
