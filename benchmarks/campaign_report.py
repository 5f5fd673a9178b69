"""The report of learning campaigns (``campaign.py``), built from their storage alone (no rerun).

Table 1's layout (max average return, mean +- half a std over seeds, per task and variant, with each variant's
ratio to the baseline), beside the paper's published values where the protocol is the paper's or the authors'; the
IQM of baseline-normalized scores over tasks with stratified bootstrap 95 % CIs, the probability of improvement over the
baseline and a performance profile; speed (env steps per CPU-second, wall-clock beside) and the best-so-far return
at the baseline's CPU time; each trial's time and the campaign's expected duration; learning curves per env step
and per CPU-second (one PNG, a column per task).

    python benchmarks/campaign_report.py --campaign table1 table1-default-schedule --out docs/results/paper-protocol
"""

from engine.commands import campaign_report_main

if __name__ == "__main__":
    campaign_report_main(description=__doc__)
