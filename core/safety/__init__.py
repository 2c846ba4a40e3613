"""The paper's three safety layers and the stack that runs them: strategy (danger events, the
tactile danger model, eq. 1-3 and the Bayes filter), modulation (danger potentials, eq. 4-8) and
tactile defensiveness (retraction, eq. 10-13). May import `skin`, `robot`, `design`, `sim`."""
