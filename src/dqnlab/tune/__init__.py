"""`dqnlab tune`: a study of settings on Optuna. `space.py` what is searched and how a
trial draws it; `study.py` the study directory and its Optuna study (journal storage);
`trials.py` each trial as a dqnlab run, pruned from its periodic evaluations and carried
on after a kill; `outputs.py` best.toml, trials.csv and the figures; `driver.py` a tune
from start to end, in one process or several (`--jobs`)."""
