"""Studies built on the pipeline: the paper's experiments and the demo.

- :mod:`.table1`: the paper's Table I (its rows, tasks and one job per task and seed);
  :mod:`.sweep` runs its jobs resumably and in parallel on the executors of :mod:`.executors`
  (local process pool, Ray, Dask); :mod:`.table1_report` turns the results into the table.
- :mod:`.quadrotor`: the quadrotor experiment on the Crazyflie flights (or simulated ones).
- :mod:`.demo`: ``learnest demo``, the whole pipeline on one system with figures.
- :mod:`.store`: content hashes, atomic JSON and the code hash every study records.

The names below are the Table I sweep's public API (``learnest reproduce table1``).
"""

from .executors import EXECUTOR_MODULES as EXECUTOR_MODULES
from .executors import EXECUTORS as EXECUTORS
from .executors import MissingDependencyError as MissingDependencyError
from .executors import check_executor as check_executor
from .executors import make_executor as make_executor
from .store import code_hash as code_hash
from .store import content_hash as content_hash
from .store import write_json as write_json
from .sweep import SweepReport as SweepReport
from .sweep import execute_job as execute_job
from .sweep import plan_jobs as plan_jobs
from .sweep import run_sweep as run_sweep
from .table1 import DEFAULT_TASKS as DEFAULT_TASKS
from .table1 import METHOD_LABELS as METHOD_LABELS
from .table1 import METHODS as METHODS
from .table1 import PAPER_TABLE1 as PAPER_TABLE1
from .table1 import Job as Job
from .table1 import TaskConfig as TaskConfig
from .table1 import config_summary as config_summary
from .table1 import result_path as result_path
from .table1 import run_job as run_job
from .table1 import task_configs as task_configs
from .table1_report import Table1 as Table1
from .table1_report import combine as combine
from .table1_report import gap_closure as gap_closure
from .table1_report import paper_closures as paper_closures
