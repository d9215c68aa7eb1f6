"""Imported by the local server's forkserver (:data:`flows.jobserver.PRELOAD`) and by nothing else: importing it does
once what a process's first ``calibrate`` would do (the imports, the first figure, the first flow run's imports),
so that every job process forked afterwards starts warm. multiprocessing's forkserver can only import modules before
it forks; this module is that import.
"""

import encodings.idna  # noqa: F401  (host names of the API client)

import anyio
import prefect.utilities.visualization  # noqa: F401  (the flow run's graph tracker, graphviz)

from pipeline.calibrate.fleet import prepare_worker

from . import calibrate, cli, fleet  # noqa: F401

prepare_worker()  # matplotlib's fonts, Pillow's plugins: the first figure
anyio.run(anyio.sleep, 0)  # the API client's event-loop backend (anyio's asyncio backend), its loop closed again
