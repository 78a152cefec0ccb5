"""deckland command line: closed-loop runs, campaigns, orchestration, topic and bag tools."""
