"""MetaWorld v3: tasks, initial states, the env, its scripted experts and LeRobot env config, the world."""
