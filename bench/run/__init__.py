"""The run machinery: links to the rig, the drill, the step loop, the supervisor, the safe stop and the verdict."""
