"""The safety runtime: boards' readings -> the three layers -> a robot driver, with watchdogs and a record."""
