r"""Learning campaigns as resumable Optuna studies: one study per campaign, a grid of task x variant x seed
(``GridSampler``; each worker enqueues a grid point that no trial holds, drawn at random), one training per trial.

Every trial stores, as user attributes, its evaluation curve (env steps, mean and std of the evaluation returns, the
training's CPU and wall-clock seconds at each evaluation), its CPU and wall-clock seconds (evaluation apart), env steps
per CPU-second, the package's commit and the versions of torch, SB3, gymnasium and mujoco. The report
(``campaign_report.py``) reads the storage alone.

Storage: a JournalStorage file per campaign, ``benchmarks/campaigns/<campaign>.journal``, committed with the
repository, so a campaign resumes from git on any machine; ``--storage postgresql://...`` (any SQLAlchemy URL) lets
any number of machines pull trials from one database, with Optuna's heartbeat failing the trials of dead workers and
``RetryHeartbeatStaleTrialCallback`` enqueueing them again. On a journal file, ``run`` first fails the RUNNING trials
whose worker is gone (its process on this machine, or no heartbeat for ``--stale-after`` seconds) and enqueues each
again; a trial stopped by SIGINT/SIGTERM saves a checkpoint at its next iteration boundary (protocol zoo apart), is
enqueued again too, and goes on from that checkpoint where the machine kept it. A grid point whose worker died more
than ``MAX_RETRY`` times (stops do not count) and a trial whose training raised stay failed (the report lists both;
the status shows the exception, and ``run --retry-raised`` enqueues such grid points again once the cause is mended).
``run`` makes each task left to train once before any worker starts, so that a missing dependency (Box2D, MuJoCo)
stops it with its reason. A worker out of grid points waits while others run the last ones and takes over any whose
worker dies. A task, variant and seed counts once in the report, however often it ran.

    # every campaign, its grid and how much of it is done
    python benchmarks/campaign.py status
    # the paper's Table 1, part (a): 6 tasks x {paper PPO, PPO-PeVFA OPR-E2E} x seeds 0-4, 1M steps (days of CPU)
    nohup python benchmarks/campaign.py run --campaign table1 --workers 2 > campaign.log 2>&1 &
    python benchmarks/campaign.py status --campaign table1
    # a machine lent for two hours: only runs expected to end by then, a trial still running then stopped
    python benchmarks/campaign.py run --campaign table1 --workers 2 --until +2h
    # sessions on one machine (its checkpoints stay): busy up to the deadline, the next session goes on
    python benchmarks/campaign.py run --campaign table1 --workers 2 --until 18:00 --fill
    # many machines: one database, the same command on each
    python benchmarks/campaign.py run --campaign table1 --workers 16 --storage postgresql://user:pw@host/db
    # a campaign of your own (its definition is stored in the study on creation)
    python benchmarks/campaign.py run --campaign mine --protocol sb3 --tasks Hopper-v5 --variants ppo opr \
        --seeds 0 1 --timesteps 300000
"""

from engine.commands import campaign_main

if __name__ == "__main__":
    campaign_main(description=__doc__)
