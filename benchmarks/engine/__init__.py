"""The benchmark engine behind the scripts in ``benchmarks/``: learning campaigns as resumable Optuna studies, the
trainings they run, their reports, and the zoo runs of ``learning.py``. The scripts are thin command lines over it
(``commands``); they put ``benchmarks/`` on ``sys.path`` by being run from there, as tests do by hand.

Each module imports only the ones listed before it:

- ``aggregate``: IQM, stratified bootstrap CIs and performance profiles over tasks;
- ``training_logs``: SB3's log tables parsed, and what they say after a run's peak;
- ``definitions``: protocols and their variants, ``Campaign`` and this repository's ``CAMPAIGNS``;
- ``zoo``: one rl-zoo3 training of the zoo protocol, written as a JSON record;
- ``training``: one trial's training, with its evaluation curve, its times and its checkpoints;
- ``storage``: a campaign's study in its storage, its grid points' trials, and the retries of dead workers' trials;
- ``results``: the runs, progress and notes a campaign's storage holds, its status and expected duration;
- ``deadline``: the grid points a worker takes before a deadline (``run --until``);
- ``workers``: the worker processes that train the grid points, and ``run``, which starts them;
- ``tables`` and ``figures``: the report's tables and figures; ``report``: the report in one text;
- ``zoo_report``: the report of zoo runs from their JSON records;
- ``commands``: the command lines.
"""
