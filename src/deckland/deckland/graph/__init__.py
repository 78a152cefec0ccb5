"""Graph tools: start, watch and stop the ROS 2 graph (`deckland up`, composed mode), measure
it (`deckland bench`) and view it live (Foxglove)."""
